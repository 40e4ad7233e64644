"""edygs-eval on a tiny trained run: every metric key, LPIPS reported unavailable, figures written;
plus the pose-alignment maths it relies on."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Dict

import numpy as np
import pytest
import torch
from scene_fixtures import write_processed_scene
from train_helpers import tiny_trainer_config

from edygs_ns.eval.evaluate import (
    EDI_REFERENCE,
    GRID_DIR,
    IMAGE_METRIC_KEYS,
    INITIAL_POSES_SPLIT,
    INPUT_SPLIT,
    NOVEL_SPLIT,
    NOVEL_UNFITTED_SPLIT,
    PER_VIEW_KEY,
    POSE_METRIC_KEYS,
    REGION_PSNR_KEYS,
    REFINED_POSES_SPLIT,
    TRAJECTORY_PNG,
    evaluate_run,
)
from edygs_ns.eval.lpips_loader import LPIPS_WEIGHTS_ENV
from edygs_ns.eval.pose_alignment import align_cameras, fit_gt_to_model, refined_train_poses
from edygs_ns.eval.report import LPIPS_UNAVAILABLE_TEXT
from edygs_ns.geometry import apply_sim3, to_homogeneous

#: Size of the tiny scene (SSIM needs >= 11 pixels a side).
HEIGHT, WIDTH = 24, 32
#: Training steps of the tiny run and its phase lengths (each phase is visited).
TRAIN_STEPS = 6
POSE_INIT_ITERS, STATIC_ITERS = 2, 2
#: Mask logit (m ~ 0.95, above the model's deformation threshold) given to Gaussians that must deform.
DYNAMIC_LOGIT = 3.0
#: Std of the random weights put into the deformation's position head to make renders time-dependent.
HEAD_WEIGHT_STD = 2.0


def train_tiny_run(root: Path, steps: int = TRAIN_STEPS) -> Path:
    """Write a processed fixture scene under `root`, train EDyGS on the CPU for `steps` steps, and
    return the run's config.yml (a checkpoint is saved at the last step)."""
    scene = write_processed_scene(root / "scene", n_blurry=3, k=3, height=HEIGHT, width=WIDTH, n_novel=2, n_points=150)
    config = tiny_trainer_config(scene.root, root / "runs", iters=steps, pose_init=POSE_INIT_ITERS, static=STATIC_ITERS)
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()
    return config.get_base_dir() / "config.yml"


#: The tiny run shared by every test of the session that only reads it (trained once).
_SHARED_RUN: Dict[str, Path] = {}


def shared_tiny_run(tmp_path_factory) -> Path:
    """config.yml of one tiny trained run per test session; tests must not modify its files."""
    if "config" not in _SHARED_RUN:
        _SHARED_RUN["config"] = train_tiny_run(tmp_path_factory.mktemp("shared_run"))
    return _SHARED_RUN["config"]


@pytest.fixture(scope="module")
def run_config(tmp_path_factory) -> Path:
    return shared_tiny_run(tmp_path_factory)


@pytest.fixture(autouse=True)
def no_lpips_weights(tmp_path, monkeypatch):
    """No LPIPS backbone anywhere: empty torch hub, no environment override."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    monkeypatch.delenv(LPIPS_WEIGHTS_ENV, raising=False)


def test_evaluate_run_writes_every_metric_and_figure(run_config, tmp_path):
    out = tmp_path / "eval"
    result = evaluate_run(run_config, out, max_grids=2)
    stored = json.loads((out / "metrics.json").read_text())
    assert set(stored) == set(result)
    rows = stored["edygs"]
    assert {INPUT_SPLIT, NOVEL_SPLIT, INITIAL_POSES_SPLIT, REFINED_POSES_SPLIT} <= set(rows)
    for split, n_views in ((INPUT_SPLIT, 9), (NOVEL_SPLIT, 2)):
        values = rows[split]
        assert set(IMAGE_METRIC_KEYS) <= set(values), split
        assert values["n"] == n_views
        assert math.isfinite(values["psnr"]["mean"]) and values["psnr"]["n"] == n_views
        assert -1.0 <= values["ssim"]["mean"] <= 1.0
        assert 0.0 <= values["mask_iou"]["mean"] <= 1.0
        for net in ("alex", "vgg"):  # unavailable, with a reason naming the missing weights file
            assert isinstance(values[f"lpips_{net}"], str) and ".pth" in values[f"lpips_{net}"]
        assert len(values[PER_VIEW_KEY]["psnr"]) == n_views == len(values[PER_VIEW_KEY]["time"])
    assert "fitted to its image" in rows[NOVEL_SPLIT]["note"]  # test-time pose fitting ran
    # the second protocol: the same cameras as mapped by the training-camera Sim(3), not fitted
    unfitted = rows[NOVEL_UNFITTED_SPLIT]
    assert unfitted["n"] == 2 and math.isfinite(unfitted["psnr"]["mean"]) and "fitted to its image" not in unfitted["note"]
    assert unfitted[PER_VIEW_KEY]["time"] == rows[NOVEL_SPLIT][PER_VIEW_KEY]["time"]
    # ... and written as an ns-render camera path: the same cameras, each at its own time
    from nerfstudio.cameras.camera_paths import get_path_from_json

    path = get_path_from_json(json.loads((out / "novel_camera_path.json").read_text()))
    assert path.shape[0] == 2 and path.times is not None
    assert sorted(path.times.reshape(-1).tolist()) == pytest.approx(sorted(unfitted[PER_VIEW_KEY]["time"]))
    for split in (INPUT_SPLIT, NOVEL_SPLIT, NOVEL_UNFITTED_SPLIT):  # mean rendered motion mask
        assert 0.0 <= rows[split]["mask_mean"]["mean"] <= 1.0
    for key in REGION_PSNR_KEYS:  # the fixture's masks split every view into both regions
        assert math.isfinite(rows[INPUT_SPLIT][key]["mean"]) and rows[INPUT_SPLIT][key]["n"] == 9
        assert math.isfinite(stored[EDI_REFERENCE][INPUT_SPLIT][key]["mean"])
    for split in (INITIAL_POSES_SPLIT, REFINED_POSES_SPLIT):
        assert set(POSE_METRIC_KEYS) <= set(rows[split])
        assert all(math.isfinite(rows[split][k]) for k in POSE_METRIC_KEYS)
    # the fixture's given poses are the ground truth: the initial trajectory error vanishes
    assert rows[INITIAL_POSES_SPLIT]["ate"] < 1e-5 and rows[INITIAL_POSES_SPLIT]["rpe_r"] < 1e-2
    assert math.isfinite(stored[EDI_REFERENCE][INPUT_SPLIT]["psnr"]["mean"])
    markdown = (out / "metrics.md").read_text()
    assert LPIPS_UNAVAILABLE_TEXT in markdown and INPUT_SPLIT in markdown and NOVEL_SPLIT in markdown
    grids = sorted(p.name for p in (out / GRID_DIR).glob("*.png"))
    assert grids == ["input_0000.png", "input_0008.png", "input_overview.png", "novel_0000.png", "novel_0001.png", "novel_overview.png"]
    for name in (TRAJECTORY_PNG, "psnr_over_time_input.png", "psnr_over_time_novel.png"):
        assert (out / name).stat().st_size > 0, name


def test_cli_novel_split_only(run_config, tmp_path, monkeypatch):
    from edygs_ns.scripts import eval as eval_script

    out = tmp_path / "cli"
    monkeypatch.setattr(sys, "argv", ["edygs-eval", "--load-config", str(run_config), "--output", str(out), "--split", "novel"])
    eval_script.entrypoint()
    rows = json.loads((out / "metrics.json").read_text())["edygs"]
    assert NOVEL_SPLIT in rows and INPUT_SPLIT not in rows
    assert not (out / "psnr_over_time_input.png").exists()


def test_no_unfitted_split_without_pose_fitting(run_config, tmp_path):
    """With no pose fitting, "novel views" already is the unfitted protocol: no second row."""
    from edygs_ns.eval.novel_pose_fit import NovelPoseFitConfig

    rows = evaluate_run(run_config, tmp_path / "eval", split="novel", max_grids=0, novel_pose_fit=NovelPoseFitConfig(steps=0))["edygs"]
    assert NOVEL_SPLIT in rows and NOVEL_UNFITTED_SPLIT not in rows
    assert "fitted to its image" not in rows[NOVEL_SPLIT]["note"]


def test_cli_rejects_missing_config(tmp_path):
    with pytest.raises(FileNotFoundError, match="config.yml"):
        evaluate_run(tmp_path / "nope" / "config.yml", tmp_path / "out")


def test_refined_poses_follow_the_camera_optimiser(run_config):
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(run_config, test_mode="inference")
    model = pipeline.model
    cameras = pipeline.datamanager.train_dataset.cameras
    with torch.no_grad():
        model.camera_optimizer.pose_adjustment[1, :3] += torch.tensor([0.1, -0.2, 0.05])
    refined = refined_train_poses(model, cameras)
    assert not model.training
    shift = (refined[:, :, 3] - cameras.camera_to_worlds[:, :, 3]).norm(dim=-1)
    assert shift[1] > 0.2 and float(shift[0]) < float(shift[1])


def _random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        poses[i, :3, :3] = q * np.sign(np.linalg.det(q))
        poses[i, :3, 3] = rng.normal(size=3)
    return poses


def test_novel_cameras_follow_the_training_frame():
    """A model frame that is a known similarity of the GT frame: novel GT cameras land on it."""
    from nerfstudio.cameras.cameras import Cameras

    rng = np.random.default_rng(3)
    angle = 0.7
    rot = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    sim3 = (1.7, rot, np.array([0.3, -1.0, 2.0]))
    gt_train, gt_novel = _random_poses(rng, 6), _random_poses(rng, 2)
    fitted, reason = fit_gt_to_model(gt_train, apply_sim3(gt_train, sim3))
    assert fitted is not None and reason == ""
    novel = Cameras(camera_to_worlds=torch.tensor(gt_novel[:, :3], dtype=torch.float32), fx=10.0, fy=10.0, cx=8.0, cy=6.0,
                    width=16, height=12, times=torch.tensor([[0.2], [0.8]]))  # fmt: skip
    moved = align_cameras(novel, fitted)
    np.testing.assert_allclose(to_homogeneous(moved.camera_to_worlds), apply_sim3(gt_novel, sim3), atol=1e-5)
    assert torch.equal(moved.times, novel.times)
    assert fit_gt_to_model(gt_train[:2], gt_train[:2])[0] is None


def test_the_frame_rotation_comes_from_the_camera_orientations():
    """Cameras on a straight line with centre noise: the centres alone cannot fix the rotation
    about the line, the cameras' orientations can."""
    from edygs_ns.geometry import rotation_angle
    from edygs_ns.geometry import umeyama_sim3

    rng = np.random.default_rng(5)
    n = 20
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, 0, 3] = np.linspace(-1.0, 1.0, n)  # a straight sweep along x
    gt[:, :3, 3] += rng.normal(0.0, 0.01, size=(n, 3))  # the path is not exactly straight
    angle = 0.3
    true_rot = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(angle), -np.sin(angle)], [0.0, np.sin(angle), np.cos(angle)]])  # about x
    model = apply_sim3(gt, (1.2, true_rot, np.array([0.1, 0.2, 0.3])))
    model[:, :3, 3] += rng.normal(0.0, 0.01, size=(n, 3))  # estimated centres are noisy too
    fitted, _ = fit_gt_to_model(gt, model)
    centres_only = umeyama_sim3(gt[:, :3, 3], model[:, :3, 3])
    assert np.degrees(rotation_angle(fitted[1] @ true_rot.T)) < 0.5
    assert np.degrees(rotation_angle(centres_only[1] @ true_rot.T)) > 1.5  # what centres alone give
    assert fitted[0] == pytest.approx(1.2, rel=0.02)


def test_time_sweep_renders_one_viewpoint_over_time(run_config, tmp_path):
    import shutil

    from nerfstudio.utils.eval_utils import eval_setup
    from PIL import Image

    from edygs_ns.scripts.render_time_sweep import render_time_sweep

    _, pipeline, _, _ = eval_setup(run_config, test_mode="test")
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():  # a time-dependent deformation (training leaves the heads at zero) on every Gaussian
        pipeline.model.deformation.head_xyz.weight.normal_(0.0, HEAD_WEIGHT_STD, generator=gen)
        pipeline.model.gauss_params["mask_logit"].fill_(DYNAMIC_LOGIT)
    has_ffmpeg = shutil.which("ffmpeg") is not None
    names = ("rgb", "mask", "depth")
    frames, video = render_time_sweep(pipeline, tmp_path / "sweep", camera_index=4, times=[0.0, 0.0, 1.0], output_names=names,
                                      fps=5.0, video=has_ffmpeg)  # fmt: skip
    assert len(frames) == 3
    images = [np.asarray(Image.open(f).convert("RGB"), dtype=np.int16) for f in frames]
    assert images[0].shape == (HEIGHT, WIDTH * len(names), 3)
    np.testing.assert_array_equal(images[0], images[1])  # same time, same frame
    assert np.abs(images[0] - images[2]).max() > 1  # the deformation moved the scene between t=0 and t=1
    assert (video is not None and video.stat().st_size > 0) == has_ffmpeg
    with pytest.raises(ValueError, match="camera_index"):
        render_time_sweep(pipeline, tmp_path / "bad", camera_index=99, times=[0.0], video=False)


def test_novel_pose_fit_recovers_a_perturbed_camera(run_config):
    """Frozen model, target = its own render at a pose: fitting from a pose 2 degrees and 0.05 units
    off brings the camera back and leaves the model's parameters untouched."""
    from nerfstudio.cameras.lie_groups import exp_map_SO3xR3
    from nerfstudio.utils.eval_utils import eval_setup

    from edygs_ns.eval.novel_pose_fit import NovelPoseFitConfig, fit_camera_pose
    from edygs_ns.eval.pose_alignment import with_poses
    from edygs_ns.geometry import rotation_angle

    _, pipeline, _, _ = eval_setup(run_config, test_mode="inference")
    model = pipeline.model
    model.eval()
    camera = pipeline.datamanager.train_dataset.cameras[4:5].to(model.device)
    with torch.no_grad():
        target = model.get_outputs_for_camera(camera)["rgb"]
    before = {k: v.detach().clone() for k, v in model.state_dict().items()}
    adj = exp_map_SO3xR3(torch.tensor([[0.05, -0.03, 0.02, 0.0, 0.03, -0.02]]))  # |t| 0.05, |w| 0.036 rad
    c2w = camera.camera_to_worlds
    start = with_poses(camera, torch.cat([adj[:, :3, :3] @ c2w[:, :3, :3], c2w[:, :3, 3:] + adj[:, :3, 3:]], dim=-1))
    fitted, l1_before, l1_after = fit_camera_pose(model, start, target, NovelPoseFitConfig(steps=150, lr=3e-3))
    assert l1_after < 0.3 * l1_before
    err = to_homogeneous(fitted.camera_to_worlds) @ np.linalg.inv(to_homogeneous(c2w))
    start_err = to_homogeneous(start.camera_to_worlds) @ np.linalg.inv(to_homogeneous(c2w))
    assert rotation_angle(err[0, :3, :3]) < 0.3 * rotation_angle(start_err[0, :3, :3])
    assert np.linalg.norm(err[0, :3, 3]) < 0.3 * np.linalg.norm(start_err[0, :3, 3])
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())
    assert all(p.requires_grad for p in model.gauss_params.values())


def test_region_psnr_splits_the_error_by_the_true_mask():
    from edygs_ns.eval.evaluate import region_psnr

    gt = torch.full((8, 8, 3), 0.5)
    pred = gt.clone()
    dynamic = torch.zeros(8, 8, dtype=torch.bool)
    dynamic[:2] = True
    pred[:2] += 0.1  # error only on the moving object: MSE 0.01 there
    pred[2:] += 0.01  # MSE 1e-4 elsewhere
    values = region_psnr(pred, gt, dynamic)
    assert values["psnr_dynamic"] == pytest.approx(20.0, abs=1e-3) and values["psnr_static"] == pytest.approx(40.0, abs=1e-3)
    assert region_psnr(pred, gt, None) == {}
    assert set(region_psnr(pred, gt, torch.zeros(8, 8, dtype=torch.bool))) == {"psnr_static"}


def test_covisibility_scores_split_the_error_by_what_training_saw():
    from edygs_ns.eval.evaluate import covisibility_scores

    gt = torch.full((10, 10, 3), 0.5)
    pred = gt.clone()
    seen = torch.ones(10, 10, dtype=torch.bool)
    seen[:, :2] = False  # 20 % of the pixels never seen
    pred[:, :2] += 0.1  # MSE 0.01 on the unseen pixels
    pred[:, 2:] += 0.01  # MSE 1e-4 on the seen ones
    values = covisibility_scores(pred, gt, seen)
    assert values["psnr_unseen"] == pytest.approx(20.0, abs=1e-3) and values["psnr_covisible"] == pytest.approx(40.0, abs=1e-3)
    # 20 px x 0.01 against 80 px x 1e-4: the unseen fifth carries 0.2 / 0.208 of the error
    assert values["unseen_error_share"] == pytest.approx(0.2 / 0.208, rel=1e-4)
    everything = covisibility_scores(pred, gt, torch.ones(10, 10, dtype=torch.bool))
    assert set(everything) == {"psnr_covisible"}

"""The edygs-data dataparser on tiny scenes of every layout (written by scene_fixtures)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from nerfstudio.data.dataparsers.base_dataparser import transform_poses_to_original_space
from PIL import Image
from scene_fixtures import (
    write_e2nerf_real_scene,
    write_e2nerf_synthetic_scene,
    write_processed_scene,
)

from edygs_ns.data.dataparser import EdygsDataParserConfig
from edygs_ns.preprocess.cache import CACHE_DIR_NAME
from edygs_ns.io.images import read_rgb_uint8
from edygs_ns.preprocess.e2nerf import subframe_fractions, subframe_indices
from edygs_ns.io.ply import read_ply_points, write_ply_points
from edygs_ns.events.edi import EdiConfig, edi_from_frame

#: Pose comparisons after a float32 round trip through the dataparser transform.
POSE_ATOL = 1e-4


def _parse(root: Path, split: str = "train", **kwargs):
    return EdygsDataParserConfig(data=root, **kwargs).setup().get_dataparser_outputs(split)


def _original_poses(outputs) -> np.ndarray:
    """Cameras mapped back through dataparser_transform/scale: [N, 3, 4] in the layout's frame."""
    c2w = transform_poses_to_original_space(
        outputs.cameras.camera_to_worlds, outputs.dataparser_transform, outputs.dataparser_scale, "opengl"
    )
    return c2w.numpy()[:, :3, :]


def _cache_files(root: Path):
    return {p: p.stat().st_mtime_ns for p in (root / CACHE_DIR_NAME).rglob("*") if p.is_file()}


# -- processed layout ---------------------------------------------------------------------------


def test_processed_train_split(tmp_path):
    scene = write_processed_scene(tmp_path / "scene")
    out = _parse(scene.root)
    n = scene.n_blurry * scene.k
    assert out.cameras.shape == (n,) and len(out.image_filenames) == n
    times = out.cameras.times[:, 0]
    assert times.min() >= 0.0 and times.max() <= 1.0 and torch.all(times[1:] > times[:-1])
    meta = out.metadata
    # frames are stored shuffled in transforms.json; cameras come back in (blurry, latent) order
    assert meta["blurry_index"].tolist() == [b for b in range(scene.n_blurry) for _ in range(scene.k)]
    assert meta["latent_index"].tolist() == list(range(scene.k)) * scene.n_blurry
    assert out.image_filenames[scene.k + 2] == scene.root / "latents/0001_2.png"
    assert meta["k"] == scene.k and meta["theta"] == pytest.approx(0.2) and meta["color_space"] == "linear"
    assert meta["event_maps"].dtype == torch.float32
    assert torch.equal(meta["event_maps"], torch.from_numpy(scene.event_maps))
    assert meta["points3D_xyz"].shape == (len(scene.points), 3) and meta["points3D_rgb"].dtype == torch.uint8
    assert len(meta["blurry_filenames"]) == scene.n_blurry and meta["pose_source"] == "given"
    pair = meta["latent_to_pair"].tolist()
    for i, nxt in enumerate(pair):
        assert nxt == (i + 1 if (i % scene.k) < scene.k - 1 else -1)
    np.testing.assert_allclose(_original_poses(out), scene.c2w[:, :3], atol=POSE_ATOL)
    # ground truth: per-latent sharp images, masks and poses aligned with the cameras
    assert meta["gt_image_filenames"][3] == scene.root / "gt/sharp/0000_3.png"
    assert len(meta["gt_mask_filenames"]) == n
    assert torch.allclose(meta["gt_camera_to_worlds"], out.cameras.camera_to_worlds, atol=POSE_ATOL)


def test_points_transformed_like_poses(tmp_path):
    """A point's coordinates in every camera are scaled by dataparser_scale and otherwise unchanged."""
    scene = write_processed_scene(tmp_path / "scene")
    out = _parse(scene.root, orientation_method="pca", center_method="focus")
    pts_new = out.metadata["points3D_xyz"].double()
    pts_old = torch.from_numpy(scene.points).double()
    c2w_new = out.cameras.camera_to_worlds.double()
    c2w_old = torch.from_numpy(scene.c2w)
    for i in (0, len(scene.c2w) - 1):
        cam_new = (pts_new - c2w_new[i, :3, 3]) @ c2w_new[i, :3, :3]
        cam_old = (pts_old - c2w_old[i, :3, 3]) @ c2w_old[i, :3, :3]
        assert torch.allclose(cam_new, out.dataparser_scale * cam_old, atol=1e-4)
    assert out.cameras.camera_to_worlds[:, :3, 3].abs().max() == pytest.approx(1.0, abs=1e-5)


def test_processed_novel_eval(tmp_path):
    scene = write_processed_scene(tmp_path / "scene", n_novel=3)
    train = _parse(scene.root, "train")
    out = _parse(scene.root, "val")
    assert out.cameras.shape == (3,)
    assert out.image_filenames == scene.novel_files
    np.testing.assert_allclose(out.cameras.times[:, 0].numpy(), scene.novel_times, atol=1e-6)
    np.testing.assert_allclose(_original_poses(out), scene.novel_c2w[:, :3], atol=POSE_ATOL)
    assert torch.equal(out.dataparser_transform, train.dataparser_transform)
    assert len(out.metadata["gt_mask_filenames"]) == 3 and "event_maps" not in out.metadata
    assert out.metadata["latent_index"].tolist() == [-1, -1, -1]


def test_colmap_poses_align_ground_truth(tmp_path):
    """Estimated poses in another frame: novel views are moved into it by a Sim(3) fitted on the latents."""
    scene = write_processed_scene(tmp_path / "scene", pose_source="colmap")
    meta = json.loads((scene.root / "transforms.json").read_text())
    scale, rot = 2.5, np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    sim = np.eye(4)
    sim[:3, :3], sim[:3, 3] = scale * rot, [1.0, -2.0, 0.5]
    for frame in meta["frames"]:
        c2w = sim @ np.array(frame["transform_matrix"])
        c2w[:3, :3] /= scale
        frame["transform_matrix"] = c2w.tolist()
    (scene.root / "transforms.json").write_text(json.dumps(meta))
    out = _parse(scene.root, "val")
    expected = sim[None] @ scene.novel_c2w
    expected[:, :3, :3] /= scale
    np.testing.assert_allclose(_original_poses(out), expected[:, :3], atol=1e-3)


def test_pose_errors_come_out_in_ground_truth_units(tmp_path):
    """COLMAP's frame is 2.5x the ground truth's: ATE is reported in the ground truth's units."""
    from edygs_ns.eval.pose_alignment import TrainPoses, pose_rows
    from edygs_ns.geometry import to_homogeneous
    from edygs_ns.eval.trajectory import trajectory_metrics

    scene = write_processed_scene(tmp_path / "scene", pose_source="colmap")
    meta = json.loads((scene.root / "transforms.json").read_text())
    colmap_scale = 2.5
    rng = np.random.default_rng(1)
    for frame in meta["frames"]:
        c2w = np.array(frame["transform_matrix"])
        c2w[:3, 3] = colmap_scale * (c2w[:3, 3] + rng.normal(0.0, 0.05, 3))  # 0.05 GT units of noise
        frame["transform_matrix"] = c2w.tolist()
    (scene.root / "transforms.json").write_text(json.dumps(meta))
    out = _parse(scene.root, "train")
    assert out.metadata["gt_units_scale"] == pytest.approx(colmap_scale * out.dataparser_scale, rel=0.05)
    cameras = to_homogeneous(out.cameras.camera_to_worlds)
    rows = pose_rows(TrainPoses(initial=cameras, refined=cameras, gt=to_homogeneous(out.metadata["gt_camera_to_worlds"]),
                                scale=out.metadata["gt_units_scale"]))  # fmt: skip
    stored = np.stack([np.array(f["transform_matrix"]) for f in sorted(meta["frames"], key=lambda f: f["time_us"])])
    direct = trajectory_metrics(stored, scene.c2w)["ate"]  # estimate vs the untouched ground truth
    assert 0.02 < direct < 0.1
    assert rows["poses (initial)"]["ate"] == pytest.approx(direct, rel=1e-3)


def test_fallback_to_interval_without_novel_views(tmp_path, capsys):
    scene = write_processed_scene(tmp_path / "scene", n_blurry=4, with_gt=False)
    parser = EdygsDataParserConfig(data=scene.root, eval_interval=2).setup()
    train = parser.get_dataparser_outputs("train")
    val = parser.get_dataparser_outputs("val")
    assert "falling back" in " ".join(capsys.readouterr().out.split())
    assert sorted(set(train.metadata["blurry_index"].tolist())) == [1, 3]
    assert sorted(set(val.metadata["blurry_index"].tolist())) == [0, 2]
    assert len(val.image_filenames) == 2 * scene.k and "gt_image_filenames" not in val.metadata
    assert val.image_filenames[0] == scene.root / "latents/0000_0.png"


def test_eval_mode_all(tmp_path):
    scene = write_processed_scene(tmp_path / "scene")
    test = _parse(scene.root, "test", eval_mode="all")
    assert test.cameras.shape == (scene.n_blurry * scene.k,)
    assert test.image_filenames[0] == scene.root / "gt/sharp/0000_0.png"


@pytest.mark.parametrize("k", [5, 4])
def test_blurry_source_exposure_centre(tmp_path, k):
    scene = write_processed_scene(tmp_path / "scene", k=k)
    latents = _parse(scene.root)
    out = _parse(scene.root, image_source="blurry")
    assert out.cameras.shape == (scene.n_blurry,) and out.image_filenames == scene.blurry_files
    c2w, lat = out.cameras.camera_to_worlds, latents.cameras.camera_to_worlds
    for b in range(scene.n_blurry):
        centre = [b * k + (k - 1) // 2] if k % 2 else [b * k + k // 2 - 1, b * k + k // 2]
        assert torch.allclose(c2w[b, :3, 3], lat[centre, :3, 3].mean(0), atol=1e-5)
        assert out.cameras.times[b, 0] == pytest.approx(float(latents.cameras.times[centre, 0].mean()), abs=1e-6)
        rot = c2w[b, :3, :3].double()
        assert torch.allclose(rot.T @ rot, torch.eye(3, dtype=torch.float64), atol=1e-5)


def test_event_maps_shape_mismatch(tmp_path):
    scene = write_processed_scene(tmp_path / "scene", with_gt=False)
    np.save(scene.root / "event_maps.npy", np.zeros((scene.n_blurry, scene.k, 3, 3), np.float32))
    with pytest.raises(ValueError, match=r"event_maps\.npy.*\(3, 5, 3, 3\).*\(3, 4, 12, 16\)"):
        _parse(scene.root)


def test_missing_latent_image_named(tmp_path):
    scene = write_processed_scene(tmp_path / "scene", with_gt=False)
    (scene.root / "latents/0001_3.png").unlink()
    with pytest.raises(FileNotFoundError, match="0001_3.png"):
        _parse(scene.root)


# -- E2NeRF synthetic ---------------------------------------------------------------------------


def test_subframe_indices():
    # E2NeRF: the blur averages sub-frames 0..17 and bin 0 spans sub-frames 0 -> 5.
    assert subframe_indices(18, 5).tolist() == [0, 5, 9, 13, 17]
    assert subframe_indices(21, 5).tolist() == [0, 5, 9, 13, 17]
    assert subframe_indices(18, 3).tolist() == [0, 9, 17]
    assert subframe_indices(18, 2).tolist() == [0, 17]
    assert subframe_indices(9, 5).tolist() == [0, 2, 4, 6, 8]
    np.testing.assert_allclose(subframe_fractions(18, 5), [0, 5 / 17, 9 / 17, 13 / 17, 1])
    np.testing.assert_allclose(subframe_fractions(9, 5), [0, 0.25, 0.5, 0.75, 1])
    with pytest.raises(ValueError):
        subframe_indices(3, 5)


def test_e2nerf_synthetic(tmp_path):
    scene = write_e2nerf_synthetic_scene(tmp_path / "scene")
    parser = EdygsDataParserConfig(data=scene.root).setup()
    out = parser.get_dataparser_outputs("train")
    n = scene.n_blurry * scene.k
    assert parser.scene().layout == "e2nerf-synthetic"
    assert out.cameras.shape == (n,) and out.metadata["k"] == 5
    times = out.cameras.times[:, 0]
    assert times[0] == 0.0 and times[-1] == 1.0 and torch.all(times[1:] > times[:-1])
    # latents sit at their sub-frames' instants: exposures back to back, sub-frame / 17 inside each
    slots = np.arange(scene.n_blurry)[:, None] * 5 + np.array([0, 5, 9, 13, 17]) / 17 * 4
    np.testing.assert_allclose(times.numpy(), slots.reshape(-1) / (5 * scene.n_blurry - 1), atol=1e-6)
    # latents are sub-frames 0, 5, 9, 13, 17 of each frame's 18 sub-poses
    expected = scene.c2w.reshape(scene.n_blurry, 18, 4, 4)[:, [0, 5, 9, 13, 17]].reshape(-1, 4, 4)
    np.testing.assert_allclose(_original_poses(out), expected[:, :3], atol=POSE_ATOL)
    assert torch.equal(out.metadata["event_maps"], torch.from_numpy(scene.event_maps))
    assert out.metadata["points3D_xyz"].shape[1] == 3
    # latents are EDI of the blurry frame's stored RGB: E2NeRF's white_bkgd = False drops alpha
    blurry = read_rgb_uint8(scene.blurry_files[1], background=None)
    with Image.open(scene.blurry_files[1]) as img:
        assert img.mode == "RGBA" and np.asarray(img)[0, 0, 3] == 0
        assert blurry[0, 0].tolist() == np.asarray(img)[0, 0, :3].tolist() != [255, 255, 255]
    latents = edi_from_frame(blurry, scene.event_maps[1], EdiConfig(k=5, theta=0.2))
    for j in range(scene.k):
        stored = np.asarray(Image.open(out.image_filenames[scene.k + j]), dtype=np.float32) / 255.0
        np.testing.assert_allclose(stored, latents[j], atol=0.6 / 255.0)
    assert all(p.is_relative_to(scene.root / CACHE_DIR_NAME) for p in out.image_filenames)
    val = parser.get_dataparser_outputs("val")
    assert val.cameras.shape == (2,)
    np.testing.assert_allclose(_original_poses(val), scene.novel_c2w[:, :3], atol=POSE_ATOL)
    assert ((val.cameras.times >= 0) & (val.cameras.times <= 1)).all()


def test_e2nerf_cache_is_reused_and_invalidated(tmp_path):
    scene = write_e2nerf_synthetic_scene(tmp_path / "scene")
    first = _parse(scene.root)
    before = _cache_files(scene.root)
    assert len(before) >= scene.n_blurry * scene.k
    second = _parse(scene.root)  # a new parser: reads the cache, computes nothing
    assert _cache_files(scene.root) == before
    assert second.image_filenames == first.image_filenames
    # new events -> recomputed latents in a new cache folder, the stale one removed
    events = torch.load(scene.root / "events.pt")
    torch.save(events * 2, scene.root / "events.pt")
    os.utime(scene.root / "events.pt", ns=(1, 1))
    third = _parse(scene.root)
    assert third.image_filenames[0] != first.image_filenames[0] and not first.image_filenames[0].exists()
    assert torch.equal(third.metadata["event_maps"], 2 * torch.from_numpy(scene.event_maps))


def test_events_pt_wrong_view_count(tmp_path):
    scene = write_e2nerf_synthetic_scene(tmp_path / "scene", n_views=3)
    torch.save(torch.zeros(2, 4, scene.height * scene.width), scene.root / "events.pt")
    with pytest.raises(ValueError, match=r"events\.pt.*\(2, 4, 80\).*\(3, any, 80\)"):
        _parse(scene.root)


# -- E2NeRF real --------------------------------------------------------------------------------


def test_e2nerf_real(tmp_path, capsys):
    scene = write_e2nerf_real_scene(tmp_path / "scene", n_views=3)
    out = _parse(scene.root, eval_mode="all")
    assert out.cameras.shape == (15,)
    np.testing.assert_allclose(_original_poses(out), scene.c2w[:, :3], atol=POSE_ATOL)
    assert float(out.cameras.fx[0]) == pytest.approx(20.0) and int(out.cameras.width[0]) == scene.width
    assert len(list((scene.root / CACHE_DIR_NAME).glob("edi_latents_*/*.png"))) == 15
    assert out.metadata["blurry_filenames"] == scene.blurry_files
    assert "gt_image_filenames" not in out.metadata
    _parse(scene.root, "val")  # no ground truth: falls back to interval with a warning
    assert "falling back" in " ".join(capsys.readouterr().out.split())


def test_e2nerf_real_bad_inputs(tmp_path):
    scene = write_e2nerf_real_scene(tmp_path / "scene", n_views=3)
    np.save(scene.root / "poses_bounds.npy", np.zeros((14, 17)))
    with pytest.raises(ValueError, match=r"poses_bounds\.npy.*\(14, 17\).*\(15, 17\)"):
        _parse(scene.root)
    torch.save(torch.zeros(3, 4, 7), scene.root / "events.pt")
    with pytest.raises(ValueError, match=r"events\.pt.*\(3, 4, 7\).*\(3, any, 60\)"):
        _parse(scene.root)


# -- detection, PLY, registration ---------------------------------------------------------------


def test_unknown_folder(tmp_path):
    (tmp_path / "junk.txt").write_text("x")
    with pytest.raises(ValueError, match=r"not a recognised scene folder.*transforms\.json.*events\.pt.*poses_bounds"):
        _parse(tmp_path)
    with pytest.raises(FileNotFoundError):
        _parse(tmp_path / "missing")


@pytest.mark.parametrize("binary", [True, False])
def test_ply_round_trip(tmp_path, binary):
    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(7, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, size=(7, 3), dtype=np.uint8)
    write_ply_points(tmp_path / "p.ply", xyz, rgb, binary=binary)
    got_xyz, got_rgb = read_ply_points(tmp_path / "p.ply")
    np.testing.assert_allclose(got_xyz, xyz, rtol=1e-6)
    assert np.array_equal(got_rgb, rgb)


def test_entry_point_discovered():
    from nerfstudio.plugins.registry_dataparser import discover_dataparsers

    dataparsers, descriptions = discover_dataparsers()
    assert "edygs-data" in dataparsers, "edygs_ns is not installed (pip install -e . --no-deps)"
    assert isinstance(dataparsers["edygs-data"], EdygsDataParserConfig)
    assert "E2NeRF" in descriptions["edygs-data"]

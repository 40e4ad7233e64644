"""edygs-process: input forms, COLMAP registration, the written layout, failures, resume/overwrite."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from edygs_ns.events.accumulate import exposure_bins
from edygs_ns.events.edi import EdiConfig
from edygs_ns.events.exposures import Exposure, read_exposures, write_exposures
from edygs_ns.events.readers import open_event_source, read_events
from edygs_ns.events.types import EventArray
from edygs_ns.events.writers import write_events_h5
from edygs_ns.eval.trajectory import ate_rmse
from edygs_ns.geometry import c2w_opengl_to_colmap_w2c, colmap_w2c_to_c2w_opengl
from edygs_ns.preprocess.colmap import CameraEstimate, ColmapConfig
from edygs_ns.preprocess.inputs import InputConfig
from edygs_ns.preprocess.steps import STEP_RECORD_NAME
from edygs_ns.io.ply import read_ply_points
from edygs_ns.preprocess.writer import Undistorter, complete_poses
from edygs_ns.scripts.process import entrypoint
from edygs_ns.preprocess.pipeline import ProcessConfig, RegistrationError, process
from edygs_ns.sim.writer import SynthConfig, write_synthetic_scene

#: The tiny synthetic capture shared by the tests (COLMAP registers all of its latents).
TINY = dict(width=160, height=120, n_frames=6, k=3, supersample=1, sim_steps_per_exposure=8, n_subframes=5, novel_stride=3)
K = TINY["k"]
STEPS = ["read", "edi", "poses", "write"]
#: COLMAP at its defaults (one thread: repeatable; multi-threaded runs differ from run to run).
COLMAP = ColmapConfig()
TRANSFORMS_KEYS = {"w", "h", "fl_x", "fl_y", "cx", "cy", "camera_model", "k", "theta", "color_space", "event_maps",
                   "ply_file_path", "exposures", "pose_source", "frames"}
FRAME_KEYS = {"file_path", "transform_matrix", "time", "time_us", "blurry_index", "latent_index", "blurry_file_path"}


@pytest.fixture(scope="module")
def raw(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("raw") / "capture"
    return write_synthetic_scene(SynthConfig(output_dir=folder, **TINY))


def _config(output: Path, raw: Path, inputs: InputConfig = None, **kwargs) -> ProcessConfig:
    inputs = inputs or InputConfig(exposures=raw / "exposures.csv", events=raw / "events.h5")
    return ProcessConfig(output=output, inputs=inputs, edi=EdiConfig(k=K), colmap=COLMAP, **kwargs)


def _gt_poses(raw: Path, frames: list) -> np.ndarray:
    gt = json.loads((raw / "gt" / "transforms.json").read_text())
    table = {(f["blurry_index"], f["latent_index"]): f["transform_matrix"] for f in gt["frames"]}
    return np.array([table[(f["blurry_index"], f["latent_index"])] for f in frames])


def _check_layout(scene: Path, n: int, k: int, height: int, width: int) -> dict:
    """The processed layout is complete and consistent; returns transforms.json."""
    meta = json.loads((scene / "transforms.json").read_text())
    assert TRANSFORMS_KEYS <= set(meta)
    assert (meta["w"], meta["h"], meta["k"], meta["camera_model"]) == (width, height, k, "PINHOLE")
    assert len(meta["frames"]) == n * k
    for frame in meta["frames"]:
        assert FRAME_KEYS <= set(frame)
        assert (scene / frame["file_path"]).is_file() and (scene / frame["blurry_file_path"]).is_file()
        assert np.isfinite(frame["transform_matrix"]).all()
        assert cv2.imread(str(scene / frame["file_path"])).shape == (height, width, 3)
    times = [f["time"] for f in meta["frames"]]
    assert times[0] == 0.0 and times[-1] == 1.0 and np.all(np.diff(times) > 0)
    maps = np.load(scene / meta["event_maps"])
    assert maps.shape == (n, k - 1, height, width) and maps.dtype == np.float32
    exposures = read_exposures(scene / meta["exposures"])
    assert [e.file.parent.name for e in exposures] == ["blurry"] * n
    xyz, rgb = read_ply_points(scene / meta["ply_file_path"])
    assert len(xyz) > 0 and len(xyz) == len(rgb)
    return meta


def test_form_b_given_poses_writes_the_layout(raw: Path, tmp_path: Path) -> None:
    report = process(_config(tmp_path / "scene", raw, poses="given", given_points="random", num_random_points=500))
    scene = tmp_path / "scene"
    meta = _check_layout(scene, TINY["n_frames"], K, TINY["height"], TINY["width"])
    assert meta["pose_source"] == "given" and report["registered_latents"] == report["total_latents"] == 18
    np.testing.assert_allclose([f["transform_matrix"] for f in meta["frames"]], _gt_poses(raw, meta["frames"]), atol=1e-9)
    # The event maps are exactly the bins of the raw events over each exposure's latent times.
    with open_event_source(raw / "events.h5") as source:
        expected = exposure_bins(source, read_exposures(raw / "exposures.csv"), K)
    np.testing.assert_array_equal(np.load(scene / "event_maps.npy"), expected)
    assert (scene / "gt" / "transforms.json").is_file()
    xyz, _ = read_ply_points(scene / "sparse_pc.ply")
    assert len(xyz) == 500


def _project(points: np.ndarray, c2w: np.ndarray, meta: dict) -> tuple:
    """Pixel coordinates and depth of world points seen from an OpenGL c2w camera."""
    cam = (points - c2w[:3, 3]) @ c2w[:3, :3]
    depth = -cam[:, 2]
    u = meta["fl_x"] * cam[:, 0] / depth + meta["cx"]
    v = -meta["fl_y"] * cam[:, 1] / depth + meta["cy"]
    return u, v, depth


def test_form_b_colmap_registers_and_poses_match_ground_truth(raw: Path, tmp_path: Path) -> None:
    report = process(_config(tmp_path / "scene", raw))
    meta = _check_layout(tmp_path / "scene", TINY["n_frames"], K, TINY["height"], TINY["width"])
    assert meta["pose_source"] == "colmap"
    assert report["registered_latents"] == report["total_latents"] == 18 and report["unregistered_latents"] == []
    assert report["mean_reprojection_error_px"] < 1.0 and report["num_points"] > 0
    assert report["mover_test"]["candidates"] > 0 and not report["mover_test"]["kept"], "a small sphere carries no frame"
    est = np.array([f["transform_matrix"] for f in meta["frames"]])
    gt = _gt_poses(raw, meta["frames"])
    path_diameter = json.loads((raw / "scene.json").read_text())["camera_path_diameter"]
    assert ate_rmse(est, gt) < 0.05 * path_diameter
    # the capture's camera.json was used and kept fixed
    calibration = json.loads((raw / "camera.json").read_text())
    assert (meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"]) == pytest.approx(
        (calibration["fl_x"], calibration["fl_y"], calibration["cx"], calibration["cy"]), rel=1e-6)
    assert report["camera_setting"].startswith("calibrated") and "camera.json" in report["camera_setting"]
    # The sparse points sit in the poses' world frame: in front of a camera, inside its image.
    xyz, _ = read_ply_points(tmp_path / "scene" / "sparse_pc.ply")
    u, v, depth = _project(xyz.astype(np.float64), est[len(est) // 2], meta)
    inside = (depth > 0) & (u >= 0) & (u < meta["w"]) & (v >= 0) & (v < meta["h"])
    assert inside.mean() > 0.5


def test_colmap_at_its_defaults_repeats_exactly(raw: Path, tmp_path: Path) -> None:
    """Two runs of the same capture write the same poses and points, byte for byte."""
    assert ColmapConfig().num_threads == 1
    for name in ("a", "b"):
        process(_config(tmp_path / name, raw))
    for file in ("transforms.json", "sparse_pc.ply"):
        assert (tmp_path / "a" / file).read_bytes() == (tmp_path / "b" / file).read_bytes(), file


def _write_aedat4(raw: Path, path: Path) -> None:
    """The raw capture as a DAVIS recording: grey APS frames with exposures, and its events."""
    dv = pytest.importorskip("dv_processing")
    events = read_events(raw / "events.h5")
    exposures = read_exposures(raw / "exposures.csv")
    height, width = events.sensor_size
    writer = dv.io.MonoCameraWriter(str(path), dv.io.MonoCameraWriter.DAVISConfig("DAVIS346_test", (width, height)))
    store = dv.EventStore()
    for t, x, y, p in zip(events.t.tolist(), events.x.tolist(), events.y.tolist(), events.p.tolist()):
        store.push_back(t, x, y, p > 0)
    writer.writeEvents(store)
    for e in exposures:
        grey = cv2.cvtColor(cv2.imread(str(e.file)), cv2.COLOR_BGR2GRAY)
        writer.writeFrame(dv.Frame(e.start_us, e.end_us - e.start_us, 0, 0, grey, dv.FrameSource.SENSOR))
    del writer


def test_form_a_aedat4_goes_through_colmap(raw: Path, tmp_path: Path) -> None:
    recording = tmp_path / "capture.aedat4"
    _write_aedat4(raw, recording)
    config = ProcessConfig(output=tmp_path / "scene", inputs=InputConfig(aedat4=recording), edi=EdiConfig(k=K), colmap=COLMAP)
    with pytest.raises(ValueError, match="carries none"):
        process(replace(config, poses="given", output=tmp_path / "given"))
    report = process(config)
    assert report["input_form"] == "aedat4" and report["registered_latents"] == report["total_latents"]
    _check_layout(tmp_path / "scene", TINY["n_frames"], K, TINY["height"], TINY["width"])
    blurry = cv2.imread(str(tmp_path / "scene" / "blurry" / "0000.png"))
    assert np.array_equal(blurry[..., 0], blurry[..., 1])  # grey APS frames became grey RGB


def _featureless_capture(folder: Path, n: int = 4, size: tuple = (48, 64)) -> Path:
    """A capture whose frames are flat grey: nothing for SIFT to match."""
    (folder / "frames").mkdir(parents=True)
    rng = np.random.default_rng(0)
    exposures = []
    for i in range(n):
        path = folder / "frames" / f"{i:04d}.png"
        cv2.imwrite(str(path), np.full(size + (3,), 128, np.uint8))
        exposures.append(Exposure(i, i * 100_000, i * 100_000 + 80_000, path))
    write_exposures(folder / "exposures.csv", exposures, relative_to=folder)
    count = 2000
    t = np.sort(rng.integers(0, n * 100_000, count)).astype(np.int64)
    events = EventArray(rng.integers(0, size[1], count).astype(np.int32), rng.integers(0, size[0], count).astype(np.int32),
                        t, rng.choice(np.array([-1, 1], np.int8), count), size)
    write_events_h5(folder / "events.h5", events)
    return folder


def test_too_few_registered_stops_without_transforms(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    raw = _featureless_capture(tmp_path / "flat")
    with pytest.raises(RegistrationError, match=r"registered only 0 of 12 latent frames") as info:
        process(_config(tmp_path / "scene", raw))
    assert "0000_0.png" in str(info.value) and "--poses given" in str(info.value)
    assert not (tmp_path / "scene" / "transforms.json").exists()
    report = json.loads((tmp_path / "scene" / "process_report.json").read_text())
    assert report["status"] == "failed" and len(report["unregistered_latents"]) == 12
    # The console script exits non-zero with the message (the finished steps are reused).
    argv = ["edygs-process", "--output", str(tmp_path / "scene"), "--exposures", str(raw / "exposures.csv"),
            "--events", str(raw / "events.h5"), "--k", str(K)]
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit) as exit_info:
        entrypoint()
    assert exit_info.value.code == 1
    assert not (tmp_path / "scene" / "transforms.json").exists()


def test_rerun_reuses_steps_refuses_to_clobber_and_overwrite_redoes(raw: Path, tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    config = _config(scene, raw, poses="given", num_random_points=100)
    first = process(config)
    assert first["steps_reused"] == []
    stamp = (scene / "transforms.json").stat().st_mtime_ns
    record = json.loads((scene / STEP_RECORD_NAME).read_text())
    assert sorted(record["steps"]) == sorted(STEPS)

    again = process(config)
    assert again["steps_reused"] == STEPS
    assert (scene / "transforms.json").stat().st_mtime_ns == stamp

    changed = replace(config, edi=EdiConfig(k=2))
    with pytest.raises(FileExistsError, match="--overwrite"):
        process(changed)
    assert (scene / "transforms.json").stat().st_mtime_ns == stamp
    assert json.loads((scene / "transforms.json").read_text())["k"] == K

    redone = process(replace(changed, overwrite=True))
    assert redone["steps_reused"] == []
    meta = json.loads((scene / "transforms.json").read_text())
    assert meta["k"] == 2 and len(meta["frames"]) == TINY["n_frames"] * 2


def test_foreign_folder_is_refused_and_overwrite_keeps_foreign_files(raw: Path, tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "notes.txt").write_text("mine")
    config = _config(scene, raw, poses="given", num_random_points=100)
    with pytest.raises(FileExistsError, match="did not write"):
        process(config)
    process(replace(config, overwrite=True))
    assert (scene / "notes.txt").read_text() == "mine" and (scene / "transforms.json").is_file()
    with pytest.raises(ValueError, match="contains the input"):
        process(_config(raw, raw, poses="given"))


def test_downscale_halves_frames_intrinsics_and_averages_events(raw: Path, tmp_path: Path) -> None:
    process(_config(tmp_path / "full", raw, poses="given", num_random_points=100))
    process(_config(tmp_path / "half", raw, poses="given", num_random_points=100, inputs=InputConfig(
        exposures=raw / "exposures.csv", events=raw / "events.h5", downscale=2)))
    full = json.loads((tmp_path / "full" / "transforms.json").read_text())
    half = _check_layout(tmp_path / "half", TINY["n_frames"], K, TINY["height"] // 2, TINY["width"] // 2)
    assert half["fl_x"] == pytest.approx(full["fl_x"] / 2) and half["cx"] == pytest.approx(full["cx"] / 2)
    full_maps, half_maps = np.load(tmp_path / "full" / "event_maps.npy"), np.load(tmp_path / "half" / "event_maps.npy")
    np.testing.assert_allclose(half_maps.sum(axis=(2, 3)) * 4, full_maps.sum(axis=(2, 3)), rtol=1e-5)
    gt = json.loads((tmp_path / "half" / "gt" / "transforms.json").read_text())
    assert gt["w"] == TINY["width"] // 2 and cv2.imread(str(tmp_path / "half" / "gt" / gt["frames"][0]["file_path"])).shape[:2] == (
        TINY["height"] // 2, TINY["width"] // 2)


def test_frame_selection_renumbers_frames_and_ground_truth(raw: Path, tmp_path: Path) -> None:
    inputs = InputConfig(exposures=raw / "exposures.csv", events=raw / "events.h5", frame_start=1, frame_stride=2)
    process(_config(tmp_path / "scene", raw, poses="given", num_random_points=100, inputs=inputs))
    meta = _check_layout(tmp_path / "scene", 3, K, TINY["height"], TINY["width"])
    gt = json.loads((tmp_path / "scene" / "gt" / "transforms.json").read_text())
    assert sorted({f["source_blurry_index"] for f in gt["frames"]}) == [1, 3, 5]
    assert sorted({f["blurry_index"] for f in gt["frames"]}) == [0, 1, 2]
    raw_gt = json.loads((raw / "gt" / "transforms.json").read_text())
    raw_pose = next(f["transform_matrix"] for f in raw_gt["frames"] if (f["blurry_index"], f["latent_index"]) == (3, 1))
    ours = next(f["transform_matrix"] for f in meta["frames"] if (f["blurry_index"], f["latent_index"]) == (1, 1))
    np.testing.assert_allclose(ours, raw_pose, atol=1e-9)


def test_sensor_size_mismatch_names_both_files(raw: Path, tmp_path: Path) -> None:
    events = read_events(raw / "events.h5")
    wrong = EventArray(events.x // 2, events.y // 2, events.t, events.p, (TINY["height"] // 2, TINY["width"] // 2))
    write_events_h5(tmp_path / "small.h5", wrong)
    config = ProcessConfig(output=tmp_path / "scene", inputs=InputConfig(exposures=raw / "exposures.csv",
                           events=tmp_path / "small.h5"), edi=EdiConfig(k=K))
    with pytest.raises(ValueError, match=r"small\.h5 has a 80x60 .*frames/0000\.png is 160x120"):
        process(config)


def test_events_not_covering_an_exposure_names_the_frame(raw: Path, tmp_path: Path) -> None:
    events = read_events(raw / "events.h5")
    cut = read_exposures(raw / "exposures.csv")[3].start_us
    early = events.time_slice(int(events.t[0]), cut)
    write_events_h5(tmp_path / "early.h5", early)
    config = ProcessConfig(output=tmp_path / "scene", inputs=InputConfig(exposures=raw / "exposures.csv",
                           events=tmp_path / "early.h5"), edi=EdiConfig(k=K))
    with pytest.raises(ValueError, match=r"frame 3 \(.*0003\.png\)"):
        process(config)


def _e2nerf_blender(folder: Path, n: int = 3, size: int = 16) -> tuple:
    """A tiny E2NeRF synthetic scene: RGBA frames at even indices, 19 sub-poses each, 4 bins."""
    import torch

    (folder / "train").mkdir(parents=True)
    rng = np.random.default_rng(1)
    frames, poses = [], []
    for index in range(2 * n):
        sub = np.tile(np.eye(4), (19, 1, 1))
        sub[:, :3, 3] = rng.normal(size=(19, 3))
        frames.append({"file_path": f"./train/r_{index}", "transform_matrix": sub.tolist()})
        if index % 2 == 0:
            rgba = rng.integers(0, 256, (size, size, 4)).astype(np.uint8)
            rgba[0, 0, 3] = 0
            cv2.imwrite(str(folder / "train" / f"r_{index}.png"), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
            poses.append(sub)
    (folder / "transform_train.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": frames}))
    bins = rng.integers(-3, 4, (n, 4, size * size)).astype(np.float32)
    torch.save(torch.from_numpy(bins), folder / "events.pt")
    return np.stack(poses), bins


def test_form_c_e2nerf_synthetic_given_poses(tmp_path: Path) -> None:
    poses, bins = _e2nerf_blender(tmp_path / "e2nerf")
    config = ProcessConfig(output=tmp_path / "scene", inputs=InputConfig(e2nerf=tmp_path / "e2nerf"),
                           poses="given", num_random_points=50, random_depth_range=(2.0, 6.0))
    process(config)
    meta = _check_layout(tmp_path / "scene", 3, 5, 16, 16)
    ours = np.array([f["transform_matrix"] for f in meta["frames"]]).reshape(3, 5, 4, 4)
    np.testing.assert_allclose(ours, poses[:, [0, 5, 9, 13, 17]])  # E2NeRF: bin 0 spans sub-frames 0 -> 5
    np.testing.assert_array_equal(np.load(tmp_path / "scene" / "event_maps.npy"), bins.reshape(3, 4, 16, 16))
    assert meta["fl_x"] == pytest.approx(0.5 * 16 / np.tan(0.5 * 0.69))
    blurry = cv2.imread(str(tmp_path / "scene" / "blurry" / "0000.png"), cv2.IMREAD_UNCHANGED)
    stored = cv2.imread(str(tmp_path / "e2nerf" / "train" / "r_0.png"), cv2.IMREAD_UNCHANGED)
    assert stored[0, 0, 3] == 0 and blurry.shape[2] == 3
    np.testing.assert_array_equal(blurry, stored[..., :3])  # alpha dropped, as E2NeRF (white_bkgd = False)
    # k = 3 merges pairs of E2NeRF's four bins.
    process(replace(config, output=tmp_path / "k3", edi=EdiConfig(k=3)))
    merged = np.load(tmp_path / "k3" / "event_maps.npy")
    np.testing.assert_array_equal(merged, bins.reshape(3, 2, 2, 16, 16).sum(axis=2))


def test_form_c_e2nerf_real_llff_axes(tmp_path: Path) -> None:
    import torch

    folder = tmp_path / "real"
    (folder / "images").mkdir(parents=True)
    n, h, w, focal = 2, 12, 16, 20.0
    rng = np.random.default_rng(2)
    rows = []
    for i in range(n):
        cv2.imwrite(str(folder / "images" / f"{5 * i:03d}.jpg"), rng.integers(0, 256, (h, w, 3)).astype(np.uint8))
        for _ in range(5):
            rot, _ = np.linalg.qr(rng.normal(size=(3, 3)))
            mat = np.concatenate([rot, rng.normal(size=(3, 1)), np.array([[h], [w], [focal]])], axis=1)
            rows.append(np.concatenate([mat.reshape(-1), [0.5, 4.0]]))
    rows = np.array(rows)
    np.save(folder / "poses_bounds.npy", rows)
    torch.save(torch.zeros(n, 4, h * w), folder / "events.pt")
    process(ProcessConfig(output=tmp_path / "scene", inputs=InputConfig(e2nerf=folder), poses="given", num_random_points=20))
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    llff = rows[:, :15].reshape(-1, 3, 5)
    ours = np.array([f["transform_matrix"] for f in meta["frames"]])
    # LLFF columns (down, right, back) -> OpenGL (right, up, back).
    np.testing.assert_allclose(ours[:, :3, 0], llff[:, :, 1])
    np.testing.assert_allclose(ours[:, :3, 1], -llff[:, :, 0])
    np.testing.assert_allclose(ours[:, :3, 2:4], llff[:, :, 2:4])
    assert meta["fl_x"] == pytest.approx(focal)


def test_colmap_pose_conversion_round_trip_and_axes() -> None:
    rng = np.random.default_rng(3)
    rot, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rot *= np.sign(np.linalg.det(rot))
    w2c = np.concatenate([rot, rng.normal(size=(3, 1))], axis=1)
    c2w = colmap_w2c_to_c2w_opengl(w2c)
    np.testing.assert_allclose(c2w_opengl_to_colmap_w2c(c2w), w2c, atol=1e-12)
    # A point 2 units in front of the COLMAP camera (OpenCV +z) is at -z in the OpenGL camera.
    point = np.linalg.inv(np.vstack([w2c, [0, 0, 0, 1]])) @ np.array([0.0, 0.0, 2.0, 1.0])
    cam = np.linalg.inv(c2w) @ point
    np.testing.assert_allclose(cam[:3], [0.0, 0.0, -2.0], atol=1e-12)


def test_complete_poses_interpolates_unregistered_latents() -> None:
    c2w = np.tile(np.eye(4), (3, 1, 1))
    c2w[0, 0, 3], c2w[2, 0, 3] = 0.0, 2.0
    c2w[1] = np.nan
    out = complete_poses(c2w, np.array([True, False, True]), np.array([0, 50, 100]))
    np.testing.assert_allclose(out[1], np.array([[1, 0, 0, 1.0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), atol=1e-12)


def test_undistorter_maps_distorted_dots_to_pinhole_projections() -> None:
    camera = CameraEstimate(80, 60, 60.0, 60.0, 40.0, 30.0, model="OPENCV", k1=-0.25, k2=0.05, p1=0.001, p2=-0.001)
    points = np.array([[-0.4, -0.3, 1.0], [0.45, 0.35, 1.0], [0.3, -0.25, 1.0]])
    k_cv = camera.matrix()
    k_cv[:2, 2] -= 0.5
    distorted, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), k_cv, camera.distortion())
    undistort = Undistorter.from_camera(camera)
    for (x, y), point in zip(distorted.reshape(-1, 2), points):
        image = np.zeros((60, 80), np.float32)
        image[int(round(y)), int(round(x))] = 1.0
        out = undistort.apply(cv2.GaussianBlur(image, (7, 7), 1.0))
        row, col = np.unravel_index(np.argmax(out), out.shape)
        intr = undistort.intrinsics
        expected = (intr.fl_x * point[0] / point[2] + intr.cx - 0.5, intr.fl_y * point[1] / point[2] + intr.cy - 0.5)
        assert abs(col - expected[0]) <= 1.5 and abs(row - expected[1]) <= 1.5


def test_colmap_estimates_the_focal_length_without_calibration(raw: Path, tmp_path: Path) -> None:
    config = _config(tmp_path / "scene", raw)
    report = process(replace(config, colmap=replace(COLMAP, use_calibration=False)))
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    calibration = json.loads((raw / "camera.json").read_text())
    assert meta["fl_x"] != pytest.approx(calibration["fl_x"], rel=1e-3)  # estimated, not the calibration
    assert "not used" in report["camera_setting"]


def test_read_calibration_rescales_and_names_bad_files(tmp_path: Path) -> None:
    from edygs_ns.preprocess.inputs import read_calibration

    good = tmp_path / "camera.json"
    good.write_text(json.dumps({"w": 320, "h": 240, "fl_x": 300.0, "fl_y": 310.0, "cx": 161.0, "cy": 119.0}))
    intr = read_calibration(good, (120, 160))  # frames downscaled by 2
    assert (intr.width, intr.height, intr.fl_x, intr.fl_y, intr.cx, intr.cy) == (160, 120, 150.0, 155.0, 80.5, 59.5)
    angle = tmp_path / "angle.json"
    angle.write_text(json.dumps({"w": 100, "h": 50, "camera_angle_x": 2 * np.arctan(0.5)}))
    assert read_calibration(angle, (50, 100)).fl_x == pytest.approx(100.0)
    cases = {"missing.json": None, "notjson.json": "{", "nofocal.json": json.dumps({"w": 320, "h": 240}),
             "aspect.json": json.dumps({"w": 320, "h": 320, "fl_x": 300.0}),
             "negative.json": json.dumps({"w": 320, "h": 240, "fl_x": -1.0})}
    messages = {"missing.json": "not found", "notjson.json": "not valid JSON", "nofocal.json": "no focal length",
                "aspect.json": "aspect ratio", "negative.json": "must be positive"}
    for name, text in cases.items():
        path = tmp_path / name
        if text is not None:
            path.write_text(text)
        with pytest.raises((ValueError, FileNotFoundError), match=messages[name]) as err:
            read_calibration(path, (240, 320))
        assert str(path) in str(err.value)


def test_with_calibration_sets_fixed_camera_params() -> None:
    from edygs_ns.geometry import Intrinsics
    from edygs_ns.preprocess.colmap import with_calibration

    square = Intrinsics(128, 96, 110.5, 110.5, 64.0, 48.0)
    config, note = with_calibration(ColmapConfig(), square)
    assert (config.camera_model, config.camera_params, config.refine_focal_length) == ("SIMPLE_PINHOLE", "110.5,64,48", False)
    config, _ = with_calibration(ColmapConfig(), Intrinsics(128, 96, 110.0, 120.0, 64.0, 48.0))
    assert (config.camera_model, config.camera_params) == ("PINHOLE", "110,120,64,48")
    by_hand = ColmapConfig(camera_params="100,64,48")
    assert with_calibration(by_hand, square)[0] is by_hand
    assert with_calibration(ColmapConfig(use_calibration=False), square)[0].camera_params is None
    assert with_calibration(ColmapConfig(), None)[0].refine_focal_length


def test_colmap_upsampling_factor_and_camera_params() -> None:
    from edygs_ns.preprocess.colmap import MAX_UPSAMPLE, scale_camera_params, upsample_factor

    assert upsample_factor(128, 96, 512) == 4 and upsample_factor(346, 260, 512) == 2
    assert upsample_factor(640, 480, 512) == 1 and upsample_factor(128, 96, 0) == 1
    assert upsample_factor(32, 24, 512) == MAX_UPSAMPLE
    assert scale_camera_params("SIMPLE_PINHOLE", "100,64,48", 4) == "400,256,192"
    # OPENCV: focal lengths and principal point scale, distortion (normalised coordinates) does not
    assert scale_camera_params("OPENCV", "100,90,64,48,-0.2,0.05,0.001,0", 2) == "200,180,128,96,-0.2,0.05,0.001,0"


def test_upsampled_colmap_poses_are_closer_to_the_truth(raw: Path, tmp_path: Path) -> None:
    """COLMAP on the latents upsampled (the default) against the latents as they are: same capture."""
    errors = {}
    for name, resolution in (("upsampled", COLMAP.feature_resolution), ("as_is", 0)):
        assert resolution == 0 or (COLMAP.feature_resolution > TINY["width"])
        process(replace(_config(tmp_path / name, raw), colmap=replace(COLMAP, feature_resolution=resolution)))
        meta = json.loads((tmp_path / name / "transforms.json").read_text())
        assert (meta["w"], meta["h"]) == (TINY["width"], TINY["height"])
        errors[name] = ate_rmse(np.array([f["transform_matrix"] for f in meta["frames"]]), _gt_poses(raw, meta["frames"]))
    assert errors["upsampled"] < 0.8 * errors["as_is"], errors

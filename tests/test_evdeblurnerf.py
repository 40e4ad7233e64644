"""EvDeblurNeRF scenes: reading the folder, edygs-process on it, the dataparser on it, bad inputs.

The tiny scenes are written here in the authors' published form (uzh-rpg/EvDeblurNeRF README
"Folder structure"): images_1/NN.png with images_1/timestamps.npz, poses_bounds.npy (one LLFF
row per image), all_poses_bounds.npy + all_timestamps.npy, and events.h5 with root datasets
x, y, t, p (t in ns like their Blender scenes, or µs with rectified float coordinates and
ev_map.npz like their CDAVIS scenes).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import List

import cv2
import h5py
import numpy as np
import pytest

from edygs_ns.data.dataparser import EdygsDataParserConfig
from edygs_ns.data.layouts import detect_layout
from edygs_ns.preprocess.evdeblurnerf import detect_events_unit, read_evdeblurnerf_folder
from edygs_ns.events.accumulate import latent_times_us
from edygs_ns.events.edi import EdiConfig
from edygs_ns.preprocess.inputs import InputConfig
from edygs_ns.preprocess.llff import c2w_to_rows
from edygs_ns.preprocess.pipeline import ProcessConfig, process

W, H, FOCAL = 24, 16, 30.0
#: Image kinds in name order: sharp views first and last (held out), four blurry frames between.
KINDS = ["sharp", "blurry", "blurry", "blurry", "blurry", "sharp"]
#: Image i's instant (µs) and the blurry exposure length.
T0_US, PERIOD_US, EXPOSURE_US = 1_000_000, 50_000, 20_000
#: Camera path: constant rotation, centre moving linearly (slerp/lerp reproduce it exactly).
VELOCITY = np.array([0.5, -0.2, 0.1]) * 1e-6  # world units per µs
ORIGIN = np.array([0.1, 0.2, 3.0])
POSE_ATOL = 1e-4


def _rotation() -> np.ndarray:
    rot, _ = np.linalg.qr(np.random.default_rng(7).normal(size=(3, 3)))
    return rot * np.sign(np.linalg.det(rot))


def c2w_at(t_us: np.ndarray) -> np.ndarray:
    """[N, 4, 4] OpenGL camera-to-world on the scene's camera path."""
    t_us = np.asarray(t_us, dtype=np.float64).reshape(-1)
    out = np.tile(np.eye(4), (len(t_us), 1, 1))
    out[:, :3, :3] = _rotation()
    out[:, :3, 3] = ORIGIN + (t_us - T0_US)[:, None] * VELOCITY
    return out


def llff_rows(c2w: np.ndarray, near: float = 1.0, far: float = 6.0) -> np.ndarray:
    """OpenGL poses as LLFF poses_bounds rows: rotation columns (down, right, back), hwf, near, far."""
    return c2w_to_rows(c2w, H, W, FOCAL, near, far)


@dataclass
class TinyScene:
    root: Path
    starts: np.ndarray  # µs, per blurry frame
    ends: np.ndarray
    sharp_times: np.ndarray
    x: np.ndarray  # event pixel (after rounding), per event
    y: np.ndarray
    t_us: np.ndarray  # event time in µs (floored)
    p: np.ndarray  # signed polarity
    blurry_files: List[Path]

    def bins(self, k: int) -> np.ndarray:
        """[n, k-1, H, W] signed counts between consecutive latents, counted directly."""
        out = np.zeros((len(self.starts), k - 1, H, W), dtype=np.float32)
        for b, (s, e) in enumerate(zip(self.starts, self.ends)):
            edges = latent_times_us(int(s), int(e), k)
            for j in range(k - 1):
                sel = (self.t_us >= edges[j]) & (self.t_us < edges[j + 1])
                np.add.at(out[b, j], (self.y[sel], self.x[sel]), self.p[sel])
        return out


def write_scene(root: Path, unit: str = "ns", rectified: bool = False, n_events: int = 4000) -> TinyScene:
    """A tiny EvDeblurNeRF scene in the published form (see the module docstring)."""
    rng = np.random.default_rng(3)
    images = root / "images_1"
    images.mkdir(parents=True)
    mid = T0_US + PERIOD_US * np.arange(len(KINDS), dtype=np.float64)
    blurry = np.array([kind == "blurry" for kind in KINDS])
    start = np.where(blurry, mid - EXPOSURE_US / 2, mid)
    end = np.where(blurry, mid + EXPOSURE_US / 2, mid)
    files = []
    for i in range(len(KINDS)):
        path = images / f"{i:02d}.png"
        cv2.imwrite(str(path), rng.integers(30, 220, (H, W, 3)).astype(np.uint8))
        files.append(path)
    np.savez(images / "timestamps.npz", timestamps=mid, timestamps_start=start, timestamps_end=end,
             start=mid[0], end=mid[-1])
    np.save(root / "poses_bounds.npy", llff_rows(c2w_at(mid)))
    path_times = np.linspace(mid[0] - PERIOD_US, mid[-1] + PERIOD_US, 41)
    np.save(root / "all_poses_bounds.npy", llff_rows(c2w_at(path_times)))
    np.save(root / "all_timestamps.npy", path_times)

    t_us = np.sort(rng.integers(int(mid[0]) - PERIOD_US // 2, int(mid[-1]) + PERIOD_US // 2, n_events))
    xi, yi = rng.integers(0, W, n_events), rng.integers(0, H, n_events)
    p01 = rng.integers(0, 2, n_events)
    with h5py.File(root / "events.h5", "w") as f:
        if rectified:  # CDAVIS style: rectified float coordinates, µs, and ev_map.npz
            f["x"] = (xi + rng.uniform(-0.45, 0.45, n_events)).astype(np.float32)
            f["y"] = (yi + rng.uniform(-0.45, 0.45, n_events)).astype(np.float32)
            np.savez(root / "ev_map.npz", inv_mapx=np.zeros((H, W), np.float32), inv_mapy=np.zeros((H, W), np.float32))
        else:
            f["x"], f["y"] = xi.astype(np.uint16), yi.astype(np.uint16)
        f["t"] = np.sort(t_us * 1000 + rng.integers(0, 1000, n_events)) if unit == "ns" else t_us  # sorted in ns too
        f["p"] = p01.astype(np.int8)
    return TinyScene(root, start[blurry], end[blurry], mid[~blurry], xi, yi, t_us, np.where(p01 == 1, 1.0, -1.0),
                     [files[i] for i in np.flatnonzero(blurry)])


def _process_config(scene: TinyScene, output: Path, k: int = 3, **inputs) -> ProcessConfig:
    return ProcessConfig(output=output, inputs=InputConfig(evdeblurnerf=scene.root, **inputs), edi=EdiConfig(k=k),
                         poses="given", num_random_points=50)


def _parse(root: Path, split: str = "train", **kwargs):
    return EdygsDataParserConfig(data=root, **kwargs).setup().get_dataparser_outputs(split)


def _original_poses(outputs) -> np.ndarray:
    from nerfstudio.data.dataparsers.base_dataparser import transform_poses_to_original_space

    c2w = transform_poses_to_original_space(
        outputs.cameras.camera_to_worlds, outputs.dataparser_transform, outputs.dataparser_scale, "opengl"
    )
    return c2w.numpy()[:, :3, :]


# -- reading the folder -------------------------------------------------------------------------


@pytest.mark.parametrize("unit,rectified", [("ns", False), ("us", True)])
def test_folder_reads_and_frames_exposures_events_line_up(tmp_path: Path, unit: str, rectified: bool) -> None:
    scene = write_scene(tmp_path / "scene", unit=unit, rectified=rectified)
    assert detect_layout(scene.root) == "evdeblurnerf"
    folder = read_evdeblurnerf_folder(scene.root, coordinates="round")  # bilinear: tests/test_author_formats.py
    assert folder.events_unit == unit and folder.events_unit_detected and folder.rectified_events == rectified
    assert folder.blurry == [1, 2, 3, 4] and folder.sharp == [0, 5]
    exposures = folder.exposures()
    assert [e.file for e in exposures] == scene.blurry_files
    np.testing.assert_array_equal([e.start_us for e in exposures], scene.starts)
    np.testing.assert_array_equal([e.end_us for e in exposures], scene.ends)
    intr = folder.intrinsics
    assert (intr.width, intr.height, intr.fl_x, intr.cx, intr.cy) == (W, H, FOCAL, W / 2, H / 2)
    # LLFF rows come back as the OpenGL poses they were made from; latents sit on the camera path.
    np.testing.assert_allclose(folder.image_c2w, c2w_at(T0_US + PERIOD_US * np.arange(len(KINDS))), atol=1e-9)
    latents = folder.latent_poses(exposures, 3)
    times = np.stack([latent_times_us(e.start_us, e.end_us, 3) for e in exposures])
    np.testing.assert_allclose(latents.reshape(-1, 4, 4), c2w_at(times), atol=1e-9)
    # Events in µs at the image size: one exposure's window holds exactly its events.
    with folder.open_events() as source:
        assert source.sensor_size == (H, W)
        window = source.window(int(scene.starts[1]), int(scene.ends[1]))
    sel = (scene.t_us >= scene.starts[1]) & (scene.t_us < scene.ends[1])
    np.testing.assert_array_equal(window.t, scene.t_us[sel])
    np.testing.assert_array_equal(window.x, scene.x[sel])
    np.testing.assert_array_equal(window.y, scene.y[sel])


def test_event_unit_detection_compares_spans() -> None:
    assert detect_events_unit(5e9, 5e6) == "ns"
    assert detect_events_unit(5e6, 5e6) == "us"
    assert detect_events_unit(4e6, 5e6) == "us"


# -- edygs-process -------------------------------------------------------------------------------


def test_process_given_poses_writes_a_scene_the_dataparser_loads(tmp_path: Path) -> None:
    scene = write_scene(tmp_path / "evd")
    out = tmp_path / "processed"
    report = process(_process_config(scene, out, k=3))
    assert report["input_form"] == "evdeblurnerf" and report["total_latents"] == 12
    meta = json.loads((out / "transforms.json").read_text())
    assert (meta["w"], meta["h"], meta["k"], meta["pose_source"]) == (W, H, 3, "given")
    assert meta["fl_x"] == pytest.approx(FOCAL)
    frames = meta["frames"]
    assert [f["time_us"] for f in frames] == [int(t) for s, e in zip(scene.starts, scene.ends)
                                             for t in latent_times_us(int(s), int(e), 3)]
    np.testing.assert_allclose([f["transform_matrix"] for f in frames], c2w_at([f["time_us"] for f in frames]),
                               atol=1e-9)
    np.testing.assert_array_equal(np.load(out / "event_maps.npy"), scene.bins(3))
    gt = json.loads((out / "gt" / "transforms.json").read_text())
    assert gt["frames"] == [] and len(gt["novel_frames"]) == 2
    np.testing.assert_allclose([f["transform_matrix"] for f in gt["novel_frames"]], c2w_at(scene.sharp_times),
                               atol=1e-9)
    np.testing.assert_array_equal(cv2.imread(str(out / "gt" / gt["novel_frames"][1]["file_path"])),
                                  cv2.imread(str(scene.root / "images_1" / "05.png")))

    train = _parse(out)
    assert train.cameras.shape == (12,)
    np.testing.assert_allclose(_original_poses(train), c2w_at([f["time_us"] for f in frames])[:, :3], atol=POSE_ATOL)
    novel = _parse(out, "val")
    assert novel.cameras.shape == (2,)
    times = novel.cameras.times.reshape(-1).numpy()
    assert times[0] == 0.0 and times[1] == 1.0  # sharp views before / after the clip are clamped


def test_process_downscale_and_frame_selection(tmp_path: Path) -> None:
    scene = write_scene(tmp_path / "evd")
    out = tmp_path / "processed"
    process(_process_config(scene, out, k=2, frame_start=1, frame_end=3, downscale=2))
    meta = json.loads((out / "transforms.json").read_text())
    assert (meta["w"], meta["h"], len(meta["frames"])) == (W // 2, H // 2, 4)
    assert meta["fl_x"] == pytest.approx(FOCAL / 2)
    expected = scene.bins(2)[1:3].reshape(2, 1, H // 2, 2, W // 2, 2).mean(axis=(3, 5))
    np.testing.assert_allclose(np.load(out / "event_maps.npy"), expected, atol=1e-6)
    gt = json.loads((out / "gt" / "transforms.json").read_text())
    assert (gt["w"], gt["h"]) == (W // 2, H // 2)


# -- the dataparser on the folder itself -----------------------------------------------------------


def test_dataparser_reads_the_folder_directly_and_caches(tmp_path: Path) -> None:
    scene = write_scene(tmp_path / "evd")
    train = _parse(scene.root, k=3)
    assert train.cameras.shape == (12,)
    times = np.stack([latent_times_us(int(s), int(e), 3) for s, e in zip(scene.starts, scene.ends)]).reshape(-1)
    np.testing.assert_allclose(_original_poses(train), c2w_at(times)[:, :3], atol=POSE_ATOL)
    np.testing.assert_array_equal(train.metadata["event_maps"].numpy(), scene.bins(3))
    assert train.metadata["blurry_filenames"] == scene.blurry_files
    stamps = train.cameras.times.reshape(-1).numpy()
    np.testing.assert_allclose(stamps, (times - times[0]) / (times[-1] - times[0]), atol=1e-6)
    novel = _parse(scene.root, "val", k=3)
    assert novel.cameras.shape == (2,)
    assert [Path(p).name for p in novel.image_filenames] == ["00.png", "05.png"]
    cache = {p: p.stat().st_mtime_ns for p in (scene.root / "edygs_cache").rglob("*") if p.is_file()}
    _parse(scene.root, k=3)
    assert {p: p.stat().st_mtime_ns for p in (scene.root / "edygs_cache").rglob("*") if p.is_file()} == cache


# -- bad input -------------------------------------------------------------------------------------


def test_missing_files_are_named(tmp_path: Path) -> None:
    scene = write_scene(tmp_path / "evd")
    (scene.root / "events.h5").rename(tmp_path / "events.h5")
    with pytest.raises(FileNotFoundError, match=r"events\.h5: event file not found"):
        process(_process_config(scene, tmp_path / "out"))
    (tmp_path / "events.h5").rename(scene.root / "events.h5")
    (scene.root / "images_1" / "timestamps.npz").unlink()
    with pytest.raises(FileNotFoundError, match=r"timestamps\.npz"):
        process(_process_config(scene, tmp_path / "out"))
    with pytest.raises(FileNotFoundError, match=r"missing: EvDeblurNeRF scene folder not found"):
        read_evdeblurnerf_folder(tmp_path / "missing")


def test_malformed_files_are_named(tmp_path: Path) -> None:
    scene = write_scene(tmp_path / "evd")
    rows = np.load(scene.root / "poses_bounds.npy")
    np.save(scene.root / "poses_bounds.npy", rows[:-1])
    with pytest.raises(ValueError, match=r"poses_bounds\.npy: has 5 rows, expected 6"):
        read_evdeblurnerf_folder(scene.root)
    np.save(scene.root / "poses_bounds.npy", rows)
    stamps = dict(np.load(scene.root / "images_1" / "timestamps.npz"))
    np.savez(scene.root / "images_1" / "timestamps.npz", **dict(stamps, timestamps_end=stamps["timestamps_end"][:4]))
    with pytest.raises(ValueError, match=r"timestamps\.npz: 'timestamps_end' has shape \(4,\), expected \(6,\)"):
        read_evdeblurnerf_folder(scene.root)
    del stamps["timestamps_start"]
    np.savez(scene.root / "images_1" / "timestamps.npz", **stamps)
    with pytest.raises(ValueError, match=r"timestamps\.npz: missing key\(s\) \['timestamps_start'\]"):
        read_evdeblurnerf_folder(scene.root)


def test_events_outside_the_sensor_name_the_file(tmp_path: Path) -> None:
    scene = write_scene(tmp_path / "evd")
    with h5py.File(scene.root / "events.h5", "r+") as f:
        x = f["x"][:]
        inside = np.flatnonzero((scene.t_us >= scene.starts[0]) & (scene.t_us < scene.ends[0]))
        x[inside[0]] = W  # one column past the image's right edge
        f["x"][:] = x
    with pytest.raises(ValueError, match=r"events\.h5.*lie outside the sensor \(height=16, width=24\)"):
        process(_process_config(scene, tmp_path / "out"))
    with pytest.raises(ValueError, match=r"events\.h5.*lie outside the sensor"):
        _parse(scene.root)


def test_events_not_covering_an_exposure_name_the_file_and_frame(tmp_path: Path) -> None:
    scene = write_scene(tmp_path / "evd")
    keep = scene.t_us < scene.starts[2]
    with h5py.File(scene.root / "events.h5", "r+") as f:
        columns = {k: f[k][:][keep] for k in "xytp"}
        for k in "xytp":
            del f[k]
            f[k] = columns[k]
    with pytest.raises(ValueError, match=r"events\.h5: events cover .* but frame 2 \(.*03\.png\).*read in ns \(detected\)"):
        process(_process_config(scene, tmp_path / "out"))
    with pytest.raises(ValueError, match=r"events\.h5: events cover .* frame 2 \(.*03\.png\)"):
        _parse(scene.root)
    # Forcing the wrong unit shows up the same way, naming the unit that was used.
    with pytest.raises(ValueError, match=r"events\.h5: events cover .*read in us:"):
        process(_process_config(write_scene(tmp_path / "evd2"), tmp_path / "out2", evdeblurnerf_events_unit="us"))


def test_rectified_events_rounding_outside_the_image_are_dropped(tmp_path: Path) -> None:
    scene = write_scene(tmp_path / "evd", unit="us", rectified=True)
    with h5py.File(scene.root / "events.h5", "r+") as f:
        x = f["x"][:]
        inside = np.flatnonzero((scene.t_us >= scene.starts[0]) & (scene.t_us < scene.ends[0]))
        x[inside[:3]] = [-0.7, W - 0.4, W + 2.0]  # round to -1, W, W + 2: off the undistorted image
        f["x"][:] = x
    folder = read_evdeblurnerf_folder(scene.root, coordinates="round")
    with folder.open_events() as source:
        window = source.window(int(scene.starts[0]), int(scene.ends[0]))
    assert len(window) == len(inside) - 3
    np.testing.assert_array_equal(window.x, scene.x[inside[3:]])

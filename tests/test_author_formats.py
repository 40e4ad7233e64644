"""Published formats read as their authors read them (issue 16, item 5).

- E2NeRF real: EDI Θ = 0.3 by default (its EDI.py); bins are its fixed 25.001 ms windows, so the
  nominal exposure is 4 x 25.001 ms; ``event.pt`` and 4-D ``(view, bin, H, W)`` tensors.
- E2NeRF synthetic: no compositing on white (its ``white_bkgd = False``: alpha dropped, stored RGB
  kept), latents at sub-frames 0, 5, 9, 13, 17 (bin 0 spans sub-frames 0 -> 5).
- EvDeblurNeRF: rectified float event coordinates splatted bilinearly (rounding as an option),
  camera-path translations interpolated cubically (rotations slerped), Θ 0.25 for CDAVIS scenes.
- An estimated or given Θ wins over a layout's default.

Every scene is a tiny folder written here.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import torch
from PIL import Image
from scene_fixtures import write_e2nerf_real_scene, write_e2nerf_synthetic_scene
from scipy.interpolate import interp1d
from scipy.spatial.transform import Rotation, Slerp
from test_evdeblurnerf import KINDS, PERIOD_US, T0_US, H, W, c2w_at, llff_rows, write_scene

from edygs_ns.data.layouts import read_scene
from edygs_ns.geometry import interpolate_poses
from edygs_ns.data.layouts.evdeblurnerf import read_evdeblurnerf
from edygs_ns.preprocess.evdeblurnerf import read_evdeblurnerf_folder
from edygs_ns.events.accumulate import accumulate, bin_events, latent_times_us
from edygs_ns.events.contrast import FALLBACK_THETA, ContrastEstimate, choose_theta
from edygs_ns.events.edi import EdiConfig, edi_from_frame
from edygs_ns.events.exposures import read_exposures
from edygs_ns.events.readers import ArrayEventSource, splat_bilinear
from edygs_ns.events.types import EventArray
from edygs_ns.preprocess.inputs import DownscaledEventSource, InputConfig, load_capture
from edygs_ns.preprocess.pipeline import ProcessConfig, process

# ---------------------------------------------------------------------------------- weighted events


def test_splat_bilinear_shares_drop_outside_and_keep_time_order() -> None:
    x = np.array([3.25, 0.0, -0.3, 4.5])
    y = np.array([1.0, 0.5, 2.0, 2.75])
    t = np.array([10, 20, 30, 40])
    p = np.array([1, 0, 1, 1])  # {0, 1} polarity: 0 becomes -1
    events = splat_bilinear(x, y, t, p, (4, 5), "test.h5")
    entries = {(int(a), int(b), int(c)): float(w) for a, b, c, w in zip(events.t, events.x, events.y, events.weight)}
    assert entries == pytest.approx({
        (10, 3, 1): 0.75, (10, 4, 1): 0.25,  # (3.25, 1.0): row exact, column split
        (20, 0, 0): 0.5, (20, 0, 1): 0.5,  # (0.0, 0.5)
        (30, 0, 2): 0.7,  # (-0.3, 2.0): the share at column -1 falls outside
        (40, 4, 2): 0.125, (40, 4, 3): 0.375,  # (4.5, 2.75): column 5 is outside a 5-wide sensor
    })
    assert np.all(np.diff(events.t) >= 0) and events.p[events.t == 20].tolist() == [-1, -1]
    # The signed sum over the sensor is each event's polarity times its share inside.
    assert accumulate(events, 0, 100).sum() == pytest.approx(1.0 - 1.0 + 0.7 + 0.5)


def test_weights_survive_slicing_binning_and_downscaling() -> None:
    events = EventArray(
        x=np.array([0, 1, 2, 3], np.int32), y=np.array([0, 0, 1, 1], np.int32), t=np.array([0, 5, 10, 15], np.int64),
        p=np.array([1, -1, 1, 1], np.int8), sensor_size=(2, 4), weight=np.array([0.5, 0.25, 1.0, 0.125], np.float32),
    )
    sliced = events.time_slice(5, 16)
    np.testing.assert_array_equal(sliced.weight, [0.25, 1.0, 0.125])
    bins = bin_events(events, np.array([0, 10, 20]))
    assert bins[0, 0, 0] == 0.5 and bins[0, 0, 1] == -0.25 and bins[1, 1, 2] == 1.0 and bins[1, 1, 3] == 0.125
    down = DownscaledEventSource(ArrayEventSource(events), 2).read_all()
    np.testing.assert_array_equal(down.weight, events.weight)
    with pytest.raises(ValueError, match="weight"):
        EventArray(events.x, events.y, events.t, events.p, (2, 4), weight=np.ones(3, np.float32))


# ---------------------------------------------------------------------------------- EvDeblurNeRF


def _h5_events(root: Path):
    with h5py.File(root / "events.h5", "r") as f:
        return f["x"][:].astype(np.float64), f["y"][:].astype(np.float64), f["t"][:].astype(np.int64), f["p"][:]


def _expected_maps(root: Path, starts, ends, k: int, bilinear: bool) -> np.ndarray:
    """[n, k-1, H, W] bins counted directly (np.add.at) from the file's float coordinates."""
    x, y, t, p = _h5_events(root)
    sign = np.where(p > 0, 1.0, -1.0)
    out = np.zeros((len(starts), k - 1, H, W))
    for b, (s, e) in enumerate(zip(starts, ends)):
        edges = latent_times_us(int(s), int(e), k)
        for j in range(k - 1):
            sel = (t >= edges[j]) & (t < edges[j + 1])
            if not bilinear:
                xi, yi = np.rint(x[sel]).astype(int), np.rint(y[sel]).astype(int)
                inside = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
                np.add.at(out[b, j], (yi[inside], xi[inside]), sign[sel][inside])
                continue
            x0, y0 = np.floor(x[sel]).astype(int), np.floor(y[sel]).astype(int)
            fx, fy = x[sel] - x0, y[sel] - y0
            for dx, dy, w in [(0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)]:
                xs, ys = x0 + dx, y0 + dy
                inside = (xs >= 0) & (xs < W) & (ys >= 0) & (ys < H)
                np.add.at(out[b, j], (ys[inside], xs[inside]), (sign[sel] * w)[inside])
    return out.astype(np.float32)


def test_evdeblurnerf_rectified_events_are_splatted_bilinearly_or_rounded(tmp_path: Path) -> None:
    scene = write_scene(tmp_path / "cdavis", unit="us", rectified=True)
    with h5py.File(scene.root / "events.h5", "r+") as f:  # some shares off the image
        x = f["x"][:]
        x[:5] = [-0.4, W - 0.6, 0.0, 3.5, W - 1.0]
        f["x"][:] = x
    record = read_evdeblurnerf(scene.root, k=3)
    expected = _expected_maps(scene.root, scene.starts, scene.ends, 3, bilinear=True)
    np.testing.assert_allclose(np.asarray(record.event_maps), expected, atol=1e-5)
    assert record.notes["event_coordinates"] == "bilinear"
    # A CDAVIS scene (ev_map.npz) takes the authors' CDAVIS threshold; --theta still wins.
    assert record.theta == pytest.approx(0.25)
    assert read_evdeblurnerf(scene.root, k=3, theta=0.3).theta == pytest.approx(0.3)
    rounded = read_evdeblurnerf(scene.root, k=3, coordinates="round")
    np.testing.assert_array_equal(np.asarray(rounded.event_maps), _expected_maps(scene.root, scene.starts, scene.ends, 3, False))
    assert not np.allclose(np.asarray(rounded.event_maps), expected)
    with pytest.raises(ValueError, match="coordinates mode"):
        read_evdeblurnerf_folder(scene.root, coordinates="nearest")
    # edygs-process reads the same way, and knows the layout's default Θ.
    capture = load_capture(InputConfig(evdeblurnerf=scene.root), 3, want_given_poses=False)
    try:
        assert capture.default_theta == pytest.approx(0.25) and "CDAVIS" in capture.default_theta_origin
        window = capture.events.window(int(scene.starts[0]), int(scene.ends[0]))
        assert window.weight is not None and window.weight.min() > 0 and window.weight.max() <= 1
    finally:
        capture.close()


def test_process_splats_rectified_evdeblurnerf_events_bilinearly(tmp_path: Path) -> None:
    scene = write_scene(tmp_path / "cdavis", unit="us", rectified=True)
    config = ProcessConfig(output=tmp_path / "out", inputs=InputConfig(evdeblurnerf=scene.root), edi=_edi(k=3),
                           poses="given", given_points="random", num_random_points=20)
    process(config)
    expected = _expected_maps(scene.root, scene.starts, scene.ends, 3, bilinear=True)
    np.testing.assert_allclose(np.load(tmp_path / "out" / "event_maps.npy"), expected, atol=1e-5)


def test_evdeblurnerf_blender_scene_theta_and_integer_events(tmp_path: Path) -> None:
    scene = write_scene(tmp_path / "blender", unit="ns")
    record = read_evdeblurnerf(scene.root, k=3)
    assert record.theta == pytest.approx(0.2) and record.notes["event_coordinates"] == "integer"
    np.testing.assert_array_equal(np.asarray(record.event_maps), scene.bins(3))


def test_evdeblurnerf_camera_path_translations_are_cubic(tmp_path: Path) -> None:
    scene = write_scene(tmp_path / "evd", unit="ns")
    # A sparse camera path whose centre follows a cubic in time: a cubic spline reproduces it
    # exactly, linear interpolation does not.
    path_t = np.linspace(T0_US - PERIOD_US, T0_US + PERIOD_US * len(KINDS), 9)
    c2w = c2w_at(path_t)
    u = (path_t - T0_US) / 1e5
    c2w[:, :3, 3] += np.stack([0.3 * u**3, -0.2 * u**2, 0.1 * u**3 - u], axis=1)
    np.save(scene.root / "all_poses_bounds.npy", llff_rows(c2w))
    np.save(scene.root / "all_timestamps.npy", path_t)
    folder = read_evdeblurnerf_folder(scene.root)
    exposures = folder.exposures()
    times = np.stack([latent_times_us(e.start_us, e.end_us, 3) for e in exposures]).reshape(-1).astype(np.float64)
    latents = folder.latent_poses(exposures, 3).reshape(-1, 4, 4)
    q = (times - T0_US) / 1e5
    centre = c2w_at(times)[:, :3, 3] + np.stack([0.3 * q**3, -0.2 * q**2, 0.1 * q**3 - q], axis=1)
    np.testing.assert_allclose(latents[:, :3, 3], centre, atol=1e-9)
    linear = interpolate_poses(path_t, c2w, times, translation="linear")
    assert np.abs(linear[:, :3, 3] - centre).max() > 1e-4
    np.testing.assert_allclose(latents[:, :3, :3], c2w_at(times)[:, :3, :3], atol=1e-9)


def test_interpolate_poses_cubic_is_scipy_interp1d_cubic_and_slerp() -> None:
    rng = np.random.default_rng(0)
    times = np.cumsum(rng.uniform(1, 3, 7))
    c2w = np.tile(np.eye(4), (7, 1, 1))
    c2w[:, :3, :3] = Rotation.from_rotvec(rng.normal(size=(7, 3)) * 0.3).as_matrix()
    c2w[:, :3, 3] = rng.normal(size=(7, 3))
    query = np.linspace(times[0] - 1, times[-1] + 1, 40)  # clamped outside the known range
    out = interpolate_poses(times, c2w, query, translation="cubic")
    clamped = np.clip(query, times[0], times[-1])
    np.testing.assert_allclose(out[:, :3, 3], interp1d(times, c2w[:, :3, 3], kind="cubic", axis=0)(clamped), atol=1e-12)
    slerp = Slerp(times, Rotation.from_matrix(c2w[:, :3, :3]))(clamped).as_matrix()
    np.testing.assert_allclose(out[:, :3, :3], slerp, atol=1e-12)
    # Fewer than 4 known instants: linear.
    few = interpolate_poses(times[:3], c2w[:3], query, translation="cubic")
    np.testing.assert_allclose(few, interpolate_poses(times[:3], c2w[:3], query), atol=1e-12)
    with pytest.raises(ValueError, match="translation"):
        interpolate_poses(times, c2w, query, translation="quadratic")


# ---------------------------------------------------------------------------------- E2NeRF, read directly


def test_e2nerf_real_uses_theta_0_3_and_reads_event_pt_4d(tmp_path: Path) -> None:
    scene = write_e2nerf_real_scene(tmp_path / "real", n_views=2)
    record = read_scene(scene.root)
    assert record.layout == "e2nerf-real" and record.theta == pytest.approx(0.3)
    blurry = np.asarray(Image.open(scene.blurry_files[1]).convert("RGB"))
    latents = edi_from_frame(blurry, scene.event_maps[1], EdiConfig(k=5, theta=0.3))
    for j in range(5):
        stored = np.asarray(Image.open(record.latent_image_paths[5 + j]), dtype=np.float32) / 255.0
        np.testing.assert_allclose(stored, latents[j], atol=0.6 / 255.0)
    assert read_scene(scene.root, theta=0.2).theta == pytest.approx(0.2)
    # E2NeRF's README: event.pt holding a (view, bin, H, W) tensor.
    (scene.root / "events.pt").unlink()
    torch.save(torch.from_numpy(scene.event_maps).double(), scene.root / "event.pt")
    again = read_scene(scene.root)
    assert again.notes["events_file"] == "event.pt"
    np.testing.assert_array_equal(np.asarray(again.event_maps), scene.event_maps)
    torch.save(torch.zeros(2, 4, scene.height, scene.width + 1), scene.root / "event.pt")
    with pytest.raises(ValueError, match=r"event\.pt: event bins have shape \(2, 4, 6, 11\), expected \(2, any, 60\) or \(2, any, 6, 10\)"):
        read_scene(scene.root)


def test_e2nerf_synthetic_keeps_stored_rgb_and_reads_event_pt(tmp_path: Path) -> None:
    scene = write_e2nerf_synthetic_scene(tmp_path / "syn", n_views=2)
    rgba = np.asarray(Image.open(scene.novel_files[0])).copy()
    rgba[1, 2, 3] = 0  # a transparent pixel in a test view: E2NeRF keeps its stored RGB
    Image.fromarray(rgba).save(scene.novel_files[0])
    (scene.root / "events.pt").rename(scene.root / "event.pt")
    record = read_scene(scene.root)
    assert record.layout == "e2nerf-synthetic" and record.theta == pytest.approx(0.2)
    for original, cached in zip(scene.blurry_files, record.blurry_image_paths):
        np.testing.assert_array_equal(np.asarray(Image.open(cached)), np.asarray(Image.open(original))[..., :3])
    np.testing.assert_array_equal(np.asarray(Image.open(record.novel.image_paths[0])), rgba[..., :3])
    assert record.notes["background"].startswith("none")


# ---------------------------------------------------------------------------------- E2NeRF, edygs-process


def _tiny_e2nerf_real(folder: Path, n: int = 2, h: int = 12, w: int = 16) -> None:
    (folder / "images").mkdir(parents=True)
    rng = np.random.default_rng(5)
    rows = []
    for i in range(n):
        cv2.imwrite(str(folder / "images" / f"{5 * i:03d}.jpg"), rng.integers(40, 200, (h, w, 3)).astype(np.uint8))
        for j in range(5):
            mat = np.concatenate([np.eye(3)[:, [1, 0, 2]] * [1, 1, -1], [[0.1 * (5 * i + j)], [0], [0]], [[h], [w], [20.0]]], axis=1)
            rows.append(np.concatenate([mat.reshape(-1), [0.5, 4.0]]))
    np.save(folder / "poses_bounds.npy", np.array(rows))
    torch.save(torch.from_numpy(rng.integers(-2, 3, (n, 4, h * w)).astype(np.float32)), folder / "events.pt")


def test_process_e2nerf_real_theta_and_bin_clock(tmp_path: Path) -> None:
    folder = tmp_path / "real"
    _tiny_e2nerf_real(folder)
    config = ProcessConfig(output=tmp_path / "scene", inputs=InputConfig(e2nerf=folder), poses="given",
                           given_points="random", num_random_points=20)
    report = process(config)
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    assert meta["theta"] == pytest.approx(0.3) and report["theta_source"] == "fallback"
    # E2NeRF's bins are fixed 25.001 ms windows: four of them make the nominal exposure.
    exposures = read_exposures(tmp_path / "scene" / meta["exposures"])
    assert [e.end_us - e.start_us for e in exposures] == [4 * 25_001] * 2
    steps = np.diff([f["time_us"] for f in meta["frames"][:5]])
    assert steps.tolist() == [25_001] * 4
    given = process(ProcessConfig(output=tmp_path / "given", inputs=InputConfig(e2nerf=folder), poses="given",
                                  given_points="random", num_random_points=20, edi=_edi(theta=0.25)))
    assert given["theta"] == pytest.approx(0.25) and given["theta_source"] == "given"


def _edi(**kwargs):
    from edygs_ns.preprocess.pipeline import ProcessEdiConfig

    return ProcessEdiConfig(**kwargs)


def test_process_e2nerf_synthetic_alpha_option(tmp_path: Path) -> None:
    scene = write_e2nerf_synthetic_scene(tmp_path / "syn", n_views=2, height=8, width=10)
    base = dict(poses="given", given_points="random", num_random_points=20, random_depth_range=(2.0, 6.0))
    report = process(ProcessConfig(output=tmp_path / "out", inputs=InputConfig(e2nerf=scene.root), **base))
    assert report["theta"] == pytest.approx(FALLBACK_THETA)
    stored = np.asarray(Image.open(scene.blurry_files[0]))
    ours = cv2.cvtColor(cv2.imread(str(tmp_path / "out" / "blurry" / "0000.png")), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(ours, stored[..., :3])
    # --alpha-background white composites as before (the transparent pixel turns white).
    process(ProcessConfig(output=tmp_path / "white", inputs=InputConfig(e2nerf=scene.root, alpha_background="white"), **base))
    white = cv2.imread(str(tmp_path / "white" / "blurry" / "0000.png"))
    assert stored[0, 0, 3] == 0 and (white[0, 0] == 255).all()


# ---------------------------------------------------------------------------------- Θ precedence


def test_theta_precedence_given_then_estimate_then_layout_default() -> None:
    estimate = ContrastEstimate(theta=0.27, theta_pos=0.28, theta_neg=0.26, spread=0.01, n_pixels=500, n_pairs=3,
                                residual_scale=0.05)
    assert choose_theta(estimate, 0.4, "", 0.3, "E2NeRF").theta == 0.4
    chosen = choose_theta(estimate, None, "", 0.3, "E2NeRF")
    assert (chosen.theta, chosen.source) == (0.27, "estimated")
    fallback = choose_theta(None, None, "pre-binned", 0.3, "E2NeRF's real-data EDI value")
    assert (fallback.theta, fallback.source) == (0.3, "fallback")
    assert "Θ = 0.3 (E2NeRF's real-data EDI value)" in fallback.line()
    assert type(fallback).from_dict(fallback.to_dict()) == fallback
    assert choose_theta(None, None, "no events").theta == FALLBACK_THETA


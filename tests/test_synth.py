"""Tests of the built-in synthetic scene writer (edygs_ns.sim.scene / trajectory, edygs-synth)."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Dict

import h5py
import numpy as np
import pytest
from PIL import Image

from edygs_ns.events.exposures import read_exposures
from edygs_ns.scripts.synth import entrypoint
from edygs_ns.sim.writer import SynthConfig, SynthWorld, build_world, write_synthetic_scene
from edygs_ns.sim.scene import render, to_grey
from edygs_ns.sim.simulator import SimulatorConfig
from edygs_ns.sim.trajectory import look_at

WIDTH, HEIGHT, N_FRAMES, K = 48, 36, 4, 5
#: One 8-bit quantisation step plus float slack.
QUANT_TOL = 0.5 / 255 + 1e-4


def tiny_config(out: Path, **changes) -> SynthConfig:
    base = SynthConfig(output_dir=out, width=WIDTH, height=HEIGHT, n_frames=N_FRAMES, k=K, n_subframes=9,
                       sim_steps_per_exposure=16, novel_stride=2)
    return dataclasses.replace(base, **changes)


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    return write_synthetic_scene(tiny_config(tmp_path_factory.mktemp("synth") / "raw"))


@pytest.fixture(scope="module")
def world(capture: Path) -> SynthWorld:
    """The world the capture was rendered from (rebuilt from the same config)."""
    return build_world(tiny_config(capture))


def load_png(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path)).astype(np.float64) / 255.0


def load_events(folder: Path) -> Dict[str, np.ndarray]:
    with h5py.File(folder / "events.h5", "r") as f:
        out = {name: f[name][:] for name in ("x", "y", "t", "p")}
        out["sensor_size"] = np.asarray(f.attrs["sensor_size"])
    return out


def gt(folder: Path) -> dict:
    return json.loads((folder / "gt" / "transforms.json").read_text())


def test_layout_files(capture: Path) -> None:
    lines = (capture / "exposures.csv").read_text().splitlines()
    assert lines[0] == "frame,exposure_start_us,exposure_end_us,file"
    exposures = read_exposures(capture / "exposures.csv")
    assert [e.frame for e in exposures] == list(range(N_FRAMES))
    for e in exposures:
        assert e.end_us - e.start_us == SynthConfig.exposure_us
        img = np.asarray(Image.open(e.file))
        assert img.shape == (HEIGHT, WIDTH, 3) and img.dtype == np.uint8
    assert lines[1].endswith(",frames/0000.png")
    ev = load_events(capture)
    assert tuple(ev["sensor_size"]) == (HEIGHT, WIDTH)
    assert ev["t"].dtype == np.int64 and ev["p"].dtype == np.int8
    meta = gt(capture)
    assert (meta["w"], meta["h"], meta["camera_model"], meta["k"]) == (WIDTH, HEIGHT, "PINHOLE", K)
    assert len(meta["frames"]) == N_FRAMES * K
    assert len(meta["novel_frames"]) == len(range(0, N_FRAMES, 2))
    keys = {"file_path", "mask_path", "instance_path", "transform_matrix", "time", "time_us", "blurry_index",
            "latent_index"}
    for record in meta["frames"] + meta["novel_frames"]:
        assert set(record) >= keys
        for key in ("file_path", "mask_path", "instance_path"):
            assert (capture / "gt" / record[key]).is_file()
    assert meta["frames"][2]["file_path"] == "sharp/0000_2.png"
    assert meta["novel_frames"][0]["file_path"].startswith("novel/")
    scene = json.loads((capture / "scene.json").read_text())
    assert scene["n_events"] == len(ev["t"])
    assert scene["camera_path_diameter"] > 0 and scene["room_diameter"] > scene["camera_path_diameter"]
    assert scene["config"]["width"] == WIDTH


def test_latent_times(capture: Path) -> None:
    exposures = read_exposures(capture / "exposures.csv")
    frames = gt(capture)["frames"]
    times = np.array([f["time"] for f in frames])
    assert times[0] == 0.0 and times[-1] == 1.0 and np.all(np.diff(times) > 0)
    for f in frames:
        e = exposures[f["blurry_index"]]
        expected = e.start_us + f["latent_index"] * (e.end_us - e.start_us) / (K - 1)
        assert abs(f["time_us"] - expected) <= 1


def test_blurry_frame_is_mean_of_sharp_subframes(capture: Path, world: SynthWorld) -> None:
    exposures = read_exposures(capture / "exposures.csv")
    for p in (0, N_FRAMES - 1):
        mean = np.mean([world.render(int(t))[0] for t in world.timeline.subframes[p]], axis=0)
        blurry = load_png(exposures[p].file)
        assert np.max(np.abs(blurry - mean)) <= QUANT_TOL
        sharp_mid = load_png(capture / "gt" / "sharp" / f"{p:04d}_{(K - 1) // 2}.png")
        moving = load_png(capture / "gt" / "mask" / f"{p:04d}_0.png") + load_png(capture / "gt" / "mask" / f"{p:04d}_{K - 1}.png") > 0
        diff = np.abs(blurry - sharp_mid).mean(axis=-1)
        assert diff[moving].mean() > 0.03, "object motion blur"
        assert diff[~moving].mean() > 0.005, "camera motion blur"


def test_mask_marks_moving_object(capture: Path, world: SynthWorld) -> None:
    frames = gt(capture)["frames"]
    masks = [load_png(capture / "gt" / f["mask_path"]) > 0.5 for f in frames]
    coverage = np.array([m.mean() for m in masks])
    assert np.all(coverage < 0.5) and np.mean(coverage > 0) > 0.8
    assert any(np.any(a != b) for a, b in zip(masks[:-1], masks[1:])), "mask never moves"
    # Removing the object changes the image inside its mask and nowhere else (bar edge pixels).
    f = next(f for f, m in zip(frames, masks) if m.mean() > 0.01)
    t = f["time_us"]
    rgb, instance = world.render(t)
    mask = instance > 0
    empty, empty_instance = render(world.scene, world.camera, world.c2w(t), (), world.supersample)
    assert not empty_instance.any()
    changed = np.abs(rgb - empty).max(axis=-1) > 1e-6
    assert np.array_equal(mask, load_png(capture / "gt" / f["mask_path"]) > 0.5)
    assert changed[mask].all()
    edge = changed & ~mask
    assert edge.sum() <= 0.5 * mask.sum()


def test_events_valid_and_cover_clip(capture: Path) -> None:
    ev = load_events(capture)
    t = ev["t"]
    assert len(t) > 1000
    assert np.all(np.diff(t) >= 0)
    assert ev["x"].min() >= 0 and ev["x"].max() < WIDTH and ev["y"].min() >= 0 and ev["y"].max() < HEIGHT
    assert set(np.unique(ev["p"])) == {-1, 1}
    exposures = read_exposures(capture / "exposures.csv")
    start, end = exposures[0].start_us, exposures[-1].end_us
    assert t.min() > start and t.max() <= end
    windows = np.linspace(start, end, 4 * N_FRAMES + 1)
    counts, _ = np.histogram(t, bins=windows)
    assert np.all(counts > 0), "a stretch of the clip has no events"


def summed_events(ev: Dict[str, np.ndarray], t_a: int, t_b: int) -> np.ndarray:
    """[H, W] signed event count with t_a < t <= t_b (the simulator stamps (t_prev, t_now])."""
    sel = (ev["t"] > t_a) & (ev["t"] <= t_b)
    summed = np.zeros((HEIGHT, WIDTH))
    np.add.at(summed, (ev["y"][sel], ev["x"][sel]), ev["p"][sel])
    return summed


def test_summed_events_follow_log_intensity(capture: Path, world: SynthWorld) -> None:
    config = tiny_config(capture)
    ev = load_events(capture)
    eps = SimulatorConfig().log_eps
    latents = world.timeline.latents

    def predicted(t_a: int, t_b: int) -> np.ndarray:
        grey_a, grey_b = (to_grey(world.render(int(t))[0]) for t in (t_a, t_b))
        return (np.log(grey_b + eps) - np.log(grey_a + eps)) / config.contrast_threshold

    # Each pixel's reference stays within one threshold of its log intensity, so between two
    # latents the count misses the predicted change by less than 2 (less than 1 from t = 0,
    # where the first render set the reference exactly); two independent residuals uniform in
    # (-1, 1) miss by 2/3 on average, static pixels by 0.
    for (t_a, t_b), bound in (((latents[1, 1], latents[1, 2]), 2.0), ((latents[2, 0], latents[2, K - 1]), 2.0),
                              ((latents[0, 0], latents[N_FRAMES - 1, K - 1]), 1.0)):
        pred = predicted(t_a, t_b)
        error = np.abs(summed_events(ev, t_a, t_b) - pred)
        large = np.abs(pred) >= 2.0
        assert large.mean() > 0.02, "too little change to test"
        assert error.max() < bound + 1e-6
        assert error.mean() < 0.75 and np.median(error[large] / np.abs(pred[large])) < 0.3
        assert np.array_equal(np.sign(summed_events(ev, t_a, t_b)[large]), np.sign(pred[large]))


def test_poses_valid_and_camera_moves(capture: Path, world: SynthWorld) -> None:
    poses = np.array([f["transform_matrix"] for f in gt(capture)["frames"]])
    rot = poses[:, :3, :3]
    assert np.allclose(rot @ rot.transpose(0, 2, 1), np.eye(3), atol=1e-6)
    assert np.allclose(np.linalg.det(rot), 1.0, atol=1e-6)
    assert np.allclose(poses[:, 3], [0, 0, 0, 1])
    centres = poses[:, :3, 3]
    assert np.linalg.norm(centres[-1] - centres[0]) > 0.05
    assert np.linalg.norm(centres[1] - centres[0]) > 0.0, "camera still within an exposure"
    cos = (np.trace(rot[0].T @ rot[-1]) - 1) / 2
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))) > 1.0
    # OpenGL convention: the camera's look-at point lies on its -z axis.
    for f in gt(capture)["frames"]:
        pose = np.asarray(f["transform_matrix"])
        target = world.camera_path.target(f["time_us"] / 1e6)
        in_cam = pose[:3, :3].T @ (target - pose[:3, 3])
        assert in_cam[2] < 0 and np.allclose(in_cam[:2], 0.0, atol=1e-9)


def test_novel_views_are_off_the_training_path(capture: Path) -> None:
    meta = gt(capture)
    train = np.array([f["transform_matrix"] for f in meta["frames"]])[:, :3, 3]
    by_time = {f["time_us"]: f for f in meta["frames"]}
    for novel in meta["novel_frames"]:
        centre = np.asarray(novel["transform_matrix"])[:3, 3]
        assert np.min(np.linalg.norm(train - centre, axis=1)) > 0.5 * SynthConfig.novel_offset
        same_time = by_time[novel["time_us"]]
        diff = np.abs(load_png(capture / "gt" / novel["file_path"]) - load_png(capture / "gt" / same_time["file_path"]))
        assert diff.mean() > 0.02


def test_same_seed_same_events_other_seed_different(capture: Path, tmp_path: Path) -> None:
    again = load_events(write_synthetic_scene(tiny_config(tmp_path / "again")))
    first = load_events(capture)
    for name in ("x", "y", "t", "p"):
        assert np.array_equal(again[name], first[name])
    other = load_events(write_synthetic_scene(tiny_config(tmp_path / "other", seed=1)))
    assert len(other["t"]) != len(first["t"]) or not np.array_equal(other["t"], first["t"])


def test_parallel_workers_write_the_same_capture(capture: Path, tmp_path: Path) -> None:
    again = write_synthetic_scene(tiny_config(tmp_path / "two", workers=2))
    first, second = load_events(capture), load_events(again)
    for name in ("x", "y", "t", "p"):
        assert np.array_equal(first[name], second[name])
    files = sorted(p.relative_to(capture) for p in capture.rglob("*.png"))
    assert len(files) > 20 and files == sorted(p.relative_to(again) for p in again.rglob("*.png"))
    for rel in files:
        assert (capture / rel).read_bytes() == (again / rel).read_bytes(), rel


@pytest.mark.parametrize("motion", ["linear", "bouncing"])
def test_other_motions_move_the_object(tmp_path: Path, motion: str) -> None:
    world = build_world(tiny_config(tmp_path, motion=motion))
    times = world.timeline.latents[:, 0]
    centres = np.array([world.objects[0].state(t / 1e6).centre for t in times])
    assert np.linalg.norm(np.diff(centres, axis=0), axis=1).min() > 0.01
    room_lo, room_hi = world.scene.room_min, world.scene.room_max
    assert np.all(centres > room_lo) and np.all(centres < room_hi)
    masks = [world.render(int(t))[1] > 0 for t in times]
    assert sum(m.any() for m in masks) >= len(masks) - 1


def test_refuses_to_overwrite(capture: Path, tmp_path: Path) -> None:
    with pytest.raises(FileExistsError, match=str(capture)):
        write_synthetic_scene(tiny_config(capture))
    out = tmp_path / "raw"
    (out / "frames").mkdir(parents=True)
    stale = out / "frames" / "9999.png"
    stale.write_bytes(b"old")
    keep = out / "notes.txt"
    keep.write_text("mine")
    write_synthetic_scene(tiny_config(out, n_frames=2, overwrite=True))
    assert not stale.exists() and keep.read_text() == "mine"
    assert len(read_exposures(out / "exposures.csv")) == 2


def test_bad_config_rejected(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="exposure_us"):
        write_synthetic_scene(tiny_config(tmp_path / "a", exposure_us=200_000))
    with pytest.raises(ValueError, match="supersample"):
        write_synthetic_scene(tiny_config(tmp_path / "b", supersample=0))
    assert not (tmp_path / "a").exists()


def test_cli_writes_and_summarises(tmp_path: Path, monkeypatch, capsys) -> None:
    out = tmp_path / "cli"
    argv = ["edygs-synth", "--output-dir", str(out), "--width", "32", "--height", "24", "--n-frames", "2",
            "--sim-steps-per-exposure", "8", "--motion", "linear"]
    monkeypatch.setattr(sys, "argv", argv)
    entrypoint()
    assert "2 blurry frames" in capsys.readouterr().out
    assert json.loads((out / "scene.json").read_text())["config"]["motion"] == "linear"
    assert np.asarray(Image.open(out / "frames" / "0001.png")).shape == (24, 32, 3)


def test_look_at_is_opengl() -> None:
    c2w = look_at([0.0, 0.0, 0.0], [0.0, 0.0, -1.0])
    assert np.allclose(c2w, np.eye(4))

"""Tiny scenes of every layout the edygs-data dataparser reads, written by hand into a folder.

Each writer returns a :class:`FixtureScene` holding what it wrote (poses in the layout's own
world frame, event maps, points), so tests can compare the dataparser's output with the truth.
Images are a few pixels wide; nothing here depends on the simulator.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

import numpy as np
import torch
from PIL import Image

from edygs_ns.io.ply import write_ply_points
from edygs_ns.preprocess.llff import c2w_to_rows

#: Exposure length and gap between exposures of the processed fixture, µs.
EXPOSURE_US = 40_000
FRAME_PERIOD_US = 50_000
#: Event counts per bin are drawn from [-MAX_COUNT, MAX_COUNT].
MAX_COUNT = 2
#: Focal length of the fixtures, in pixels.
FOCAL_PX = 20.0
#: Camera distance from the origin (cameras look at the origin).
CAMERA_RADIUS = 4.0
#: Angle (radians) swept by the camera over the whole fixture clip.
SWEEP_RAD = 0.6
#: LLFF near/far bounds written into poses_bounds.npy.
LLFF_NEAR, LLFF_FAR = 1.0, 10.0


@dataclass
class FixtureScene:
    """What a fixture writer put on disk.

    Attributes:
        root: the scene folder.
        c2w: [N, 4, 4] OpenGL latent poses in the layout's world frame, time order.
        event_maps: [n, k-1, H, W] float32 event counts as stored.
        n_blurry, k, height, width: scene size.
        points: [P, 3] points written to the PLY (processed layout), else None.
        novel_c2w: [V, 4, 4] novel/test view poses, or None.
        novel_times: [V] their normalised times (processed layout), or None.
        novel_files: V sharp novel images, or None.
        blurry_files: n blurry images as written.
    """

    root: Path
    c2w: np.ndarray
    event_maps: np.ndarray
    n_blurry: int
    k: int
    height: int
    width: int
    points: Optional[np.ndarray] = None
    novel_c2w: Optional[np.ndarray] = None
    novel_times: Optional[np.ndarray] = None
    novel_files: Optional[List[Path]] = None
    blurry_files: List[Path] = field(default_factory=list)


def look_at_origin(angle: float, height: float = 0.5) -> np.ndarray:
    """OpenGL c2w [4, 4] of a camera on a circle of CAMERA_RADIUS, at ``angle``, looking at the origin."""
    centre = np.array([CAMERA_RADIUS * np.sin(angle), height, CAMERA_RADIUS * np.cos(angle)])
    back = centre / np.linalg.norm(centre)
    right = np.cross([0.0, 1.0, 0.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, back, centre
    return c2w


def _trajectory(n: int) -> np.ndarray:
    return np.stack([look_at_origin(a) for a in np.linspace(-SWEEP_RAD / 2, SWEEP_RAD / 2, n)])


def _save(path: Path, pixels: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(pixels).save(path)
    return path


def _random_rgb(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    return rng.integers(30, 220, size=(height, width, 3), dtype=np.uint8)


def _random_counts(rng: np.random.Generator, shape) -> np.ndarray:
    return rng.integers(-MAX_COUNT, MAX_COUNT + 1, size=shape).astype(np.float32)


def _intrinsics(height: int, width: int) -> dict:
    return {"w": width, "h": height, "fl_x": FOCAL_PX, "fl_y": FOCAL_PX, "cx": width / 2.0, "cy": height / 2.0,
            "camera_model": "PINHOLE"}  # fmt: skip


def _latent_time_us(b: int, j: int, k: int) -> int:
    return b * FRAME_PERIOD_US + (EXPOSURE_US * j) // (k - 1)


def write_processed_scene(
    root: Path,
    n_blurry: int = 3,
    k: int = 5,
    height: int = 12,
    width: int = 16,
    with_gt: bool = True,
    n_novel: int = 2,
    n_points: int = 50,
    pose_source: str = "given",
    seed: int = 0,
) -> FixtureScene:
    """Write a processed scene (docs/layouts.md) with random images, events, points and optional gt/.

    Returns:
        The FixtureScene; novel_* are set when with_gt.
    """
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    c2w = _trajectory(n_blurry * k)
    t_first, t_last = _latent_time_us(0, 0, k), _latent_time_us(n_blurry - 1, k - 1, k)
    frames, blurry_files, exposure_rows, gt_frames = [], [], [], []
    for b in range(n_blurry):
        blurry_files.append(_save(root / f"blurry/{b:04d}.png", _random_rgb(rng, height, width)))
        exposure_rows.append(f"{b},{_latent_time_us(b, 0, k)},{_latent_time_us(b, k - 1, k)},blurry/{b:04d}.png")
        for j in range(k):
            i = b * k + j
            t_us = _latent_time_us(b, j, k)
            _save(root / f"latents/{b:04d}_{j}.png", _random_rgb(rng, height, width))
            common = {"transform_matrix": c2w[i].tolist(), "time": (t_us - t_first) / (t_last - t_first),
                      "time_us": t_us, "blurry_index": b, "latent_index": j}  # fmt: skip
            frames.append(dict(common, file_path=f"latents/{b:04d}_{j}.png", blurry_file_path=f"blurry/{b:04d}.png"))
            if with_gt:
                _save(root / f"gt/sharp/{b:04d}_{j}.png", _random_rgb(rng, height, width))
                _save(root / f"gt/mask/{b:04d}_{j}.png", (rng.random((height, width)) > 0.5).astype(np.uint8) * 255)
                gt_frames.append(dict(common, file_path=f"sharp/{b:04d}_{j}.png", mask_path=f"mask/{b:04d}_{j}.png"))
    rng_frames = list(rng.permutation(len(frames)))  # stored out of order on purpose
    event_maps = _random_counts(rng, (n_blurry, k - 1, height, width))
    np.save(root / "event_maps.npy", event_maps)
    points = rng.uniform(-1.0, 1.0, size=(n_points, 3)).astype(np.float32)
    write_ply_points(root / "sparse_pc.ply", points, rng.integers(0, 256, size=(n_points, 3), dtype=np.uint8))
    (root / "exposures.csv").write_text("frame,exposure_start_us,exposure_end_us,file\n" + "\n".join(exposure_rows) + "\n")
    meta = dict(_intrinsics(height, width), k=k, theta=0.2, color_space="linear", event_maps="event_maps.npy",
                ply_file_path="sparse_pc.ply", exposures="exposures.csv", pose_source=pose_source,
                frames=[frames[i] for i in rng_frames])  # fmt: skip
    (root / "transforms.json").write_text(json.dumps(meta, indent=1))
    scene = FixtureScene(root, c2w, event_maps, n_blurry, k, height, width, points=points, blurry_files=blurry_files)
    if with_gt:
        novel_t_us = [int(t_first + (t_last - t_first) * (v + 0.5) / n_novel) for v in range(n_novel)]
        novel_c2w = np.stack([look_at_origin(0.1 + 0.2 * v, height=0.8) for v in range(n_novel)])
        novel = []
        for v in range(n_novel):
            _save(root / f"gt/novel/{v:04d}.png", _random_rgb(rng, height, width))
            _save(root / f"gt/novel_mask/{v:04d}.png", (rng.random((height, width)) > 0.5).astype(np.uint8) * 255)
            novel.append({"file_path": f"novel/{v:04d}.png", "mask_path": f"novel_mask/{v:04d}.png",
                          "transform_matrix": novel_c2w[v].tolist(), "time_us": novel_t_us[v],
                          "time": (novel_t_us[v] - t_first) / (t_last - t_first)})  # fmt: skip
        gt_meta = dict(_intrinsics(height, width), frames=gt_frames, novel_frames=novel)
        (root / "gt/transforms.json").write_text(json.dumps(gt_meta, indent=1))
        scene.novel_c2w = novel_c2w
        scene.novel_times = np.array([n["time"] for n in novel])
        scene.novel_files = [root / "gt" / n["file_path"] for n in novel]
    return scene


def write_e2nerf_synthetic_scene(
    root: Path,
    n_views: int = 3,
    n_subframes: int = 18,
    height: int = 8,
    width: int = 10,
    n_test: int = 2,
    n_bins: int = 4,
    seed: int = 0,
) -> FixtureScene:
    """Write an E2NeRF synthetic scene: RGBA train/r_{2v}.png (even numbers, as E2NeRF), a
    transform_train.json whose frames carry n_subframes poses, events.pt [views, bins, H*W],
    and sharp RGBA test views.

    Returns:
        FixtureScene whose c2w are ALL sub-frame poses [n_views * n_subframes, 4, 4] and whose
        novel_c2w are the test poses.
    """
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    n_frames = 2 * n_views
    sub = _trajectory(n_frames * n_subframes).reshape(n_frames, n_subframes, 4, 4)
    angle = 2 * np.arctan(width / 2 / FOCAL_PX)
    frames = [{"file_path": f"./train/r_{f}", "transform_matrix": sub[f].tolist()} for f in range(n_frames)]
    (root / "transform_train.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    blurry_files = []
    for v in range(n_views):
        rgba = np.concatenate([_random_rgb(rng, height, width), np.full((height, width, 1), 255, np.uint8)], axis=-1)
        rgba[0, 0, 3] = 0  # one transparent pixel (E2NeRF drops alpha: its stored RGB stays)
        blurry_files.append(_save(root / f"train/r_{2 * v}.png", rgba))
    event_maps = _random_counts(rng, (n_views, n_bins, height, width))
    torch.save(torch.from_numpy(event_maps.astype(np.float64)).reshape(n_views, n_bins, height * width), root / "events.pt")
    test_c2w = np.stack([look_at_origin(0.05 + 0.1 * t) for t in range(n_test)])
    test_frames = [{"file_path": f"./test/r_{t}", "transform_matrix": [test_c2w[t].tolist()] * 3} for t in range(n_test)]
    (root / "transform_test.json").write_text(json.dumps({"camera_angle_x": angle, "frames": test_frames}))
    novel_files = []
    for t in range(n_test):
        rgba = np.concatenate([_random_rgb(rng, height, width), np.full((height, width, 1), 255, np.uint8)], axis=-1)
        novel_files.append(_save(root / f"test/r_{t}.png", rgba))
    return FixtureScene(
        root, sub[::2].reshape(-1, 4, 4), event_maps, n_views, n_bins + 1, height, width,
        novel_c2w=test_c2w, novel_files=novel_files, blurry_files=blurry_files,
    )  # fmt: skip


def write_e2nerf_real_scene(
    root: Path, n_views: int = 3, k: int = 5, height: int = 6, width: int = 10, seed: int = 0
) -> FixtureScene:
    """Write an E2NeRF real scene: images/{5i:03d}.jpg, poses_bounds.npy [n*k, 17] (LLFF), events.pt."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    c2w = _trajectory(n_views * k)
    np.save(root / "poses_bounds.npy", c2w_to_rows(c2w, height, width, FOCAL_PX, LLFF_NEAR, LLFF_FAR))
    blurry_files = [_save(root / f"images/{5 * v:03d}.jpg", _random_rgb(rng, height, width)) for v in range(n_views)]
    event_maps = _random_counts(rng, (n_views, k - 1, height, width))
    torch.save(torch.from_numpy(event_maps).reshape(n_views, k - 1, height * width), root / "events.pt")
    return FixtureScene(root, c2w, event_maps, n_views, k, height, width, blurry_files=blurry_files)

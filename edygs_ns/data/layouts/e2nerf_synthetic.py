"""Reader for E2NeRF's synthetic (Blender-style) scenes.

Folder::

    transform_train.json   camera_angle_x + frames; frame i carries a LIST of sub-frame poses
    transform_test.json    camera_angle_x + frames of the sharp test views (optional)
    train/r_{i}.png        blurry RGBA frame i (i need not be contiguous: E2NeRF uses even i)
    test/r_{i}.png         sharp RGBA test view i (optional)
    events.pt              float tensor [views, 4, H*W]: signed event counts, 4 bins per view

Image r_{i} of train/ goes with frame i of transform_train.json (E2NeRF's own loader pairs
``train/r_{num}.png`` with ``frames[num]``); view v of events.pt is the v-th train image in
numeric order. k = bins + 1 latents per blurry frame.

Which sub-frame poses are the latents: E2NeRF renders 18 or more sub-frames per blurry frame,
10 ms apart, and its events start at sub-frame 1 and change bin every 4 sub-frames, so the 5
latents are sub-frames 1, 5, 9, 13, 17. In general, with m >= 18 sub-frames the k latents are
the k sub-frames evenly spaced from 1 to 17 (rounded to the nearest index); with fewer
sub-frames they are k evenly spaced from 0 to m - 1. A frame with a single 4x4 pose gives
that pose to all k latents.

RGBA images are composited on WHITE (E2NeRF's ``white_bkgd`` setting) once and cached as RGB.
EDI latents are computed once from the composited blurry frames and the bins, and cached.
The scenes are static and carry no timestamps: latents are evenly spaced over [0, 1]
(exposures back to back, see common.uniform_latent_times), and each test view gets the time
of the training latent whose camera centre is nearest.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import List, Optional

import numpy as np

from edygs_ns.data.event_maps import cached_edi_latents, cached_events_pt, cached_rgb_images
from edygs_ns.data.layouts.common import (
    POSE_SIZE,
    Intrinsics,
    SceneRecord,
    ViewSet,
    as_pose,
    image_size,
    latent_grid,
    load_json,
    nearest_times,
    numbered_files,
    require_key,
    uniform_latent_times,
)
from edygs_ns.events.edi import EdiConfig

#: Train camera file.
TRAIN_TRANSFORMS = "transform_train.json"
#: Test camera file.
TEST_TRANSFORMS = "transform_test.json"
#: Event counts file.
EVENTS_FILE = "events.pt"
#: Folder of blurry training frames.
TRAIN_FOLDER = "train"
#: Folder of sharp test views.
TEST_FOLDER = "test"
#: File names of frames: r_<number>.png.
IMAGE_PATTERN = r"r_(\d+)\.png"
#: Grey level transparent pixels are composited on (white).
WHITE_BACKGROUND = 1.0
#: E2NeRF's convention for long sub-frame lists: latents span sub-frames 1..17.
E2NERF_FIRST_SUBFRAME = 1
E2NERF_LAST_SUBFRAME = 17
#: Sub-frame lists at least this long follow E2NeRF's convention.
E2NERF_MIN_SUBFRAMES = E2NERF_LAST_SUBFRAME + 1
#: Which entry of a test frame's pose list is the view (E2NeRF's loader takes entry 1).
TEST_POSE_SUBFRAME = 1
#: Default contrast threshold for E2NeRF data.
DEFAULT_THETA = 0.2
#: Default pixel encoding for E2NeRF data.
DEFAULT_COLOR_SPACE = "linear"


def is_e2nerf_synthetic(root: Path) -> bool:
    """An E2NeRF synthetic scene has transform_train.json and events.pt."""
    return (root / TRAIN_TRANSFORMS).is_file() and (root / EVENTS_FILE).is_file()


def subframe_indices(m: int, k: int) -> np.ndarray:
    """Indices of the k latent poses in a list of m sub-frame poses (see the module docstring).

    Raises:
        ValueError: m < k.
    """
    if m < k:
        raise ValueError(f"a frame has {m} sub-frame poses, fewer than k={k} latents")
    first, last = (E2NERF_FIRST_SUBFRAME, E2NERF_LAST_SUBFRAME) if m >= E2NERF_MIN_SUBFRAMES else (0, m - 1)
    return np.round(np.linspace(first, last, k)).astype(np.int64)


def _latent_poses(matrix, k: int, source: Path, frame: int) -> np.ndarray:
    """[k, 4, 4] latent poses of one frame (a list of sub-frame poses, or one pose for all)."""
    arr = np.asarray(matrix, dtype=np.float64)
    if arr.ndim == 2:
        return np.repeat(as_pose(arr, source, f"frame {frame}'s transform_matrix")[None], k, axis=0)
    if arr.ndim != 3 or arr.shape[1:] != (POSE_SIZE, POSE_SIZE):
        raise ValueError(f"{source}: frame {frame}'s transform_matrix has shape {arr.shape}, expected [m, 4, 4] or [4, 4]")
    try:
        idx = subframe_indices(arr.shape[0], k)
    except ValueError as err:
        raise ValueError(f"{source}: frame {frame}: {err}") from err
    return np.stack([as_pose(arr[i], source, f"frame {frame} sub-pose {i}") for i in idx])


def _blender_intrinsics(meta, source: Path, height: int, width: int) -> Intrinsics:
    angle = float(require_key(meta, "camera_angle_x", source))
    focal = 0.5 * width / math.tan(0.5 * angle)
    return Intrinsics(width=width, height=height, fl_x=focal, fl_y=focal, cx=width / 2.0, cy=height / 2.0)


def _numbered_images(folder: Path, source: Path, frames: List):
    """(number, path) of r_<number>.png in folder; each number must index a listed frame."""
    images = numbered_files(folder, IMAGE_PATTERN)
    for number, path in images:
        if number >= len(frames):
            raise ValueError(f"{source}: {path.name} has no frame {number} ({len(frames)} frames listed)")
    return images


def _read_test_views(root: Path, latent_c2w: np.ndarray, latent_times: np.ndarray) -> Optional[ViewSet]:
    """The sharp test views (composited on white, cached), or None if the scene has none."""
    source = root / TEST_TRANSFORMS
    if not source.is_file() or not (root / TEST_FOLDER).is_dir():
        return None
    meta = load_json(source)
    frames = list(require_key(meta, "frames", source))
    images = _numbered_images(root / TEST_FOLDER, source, frames)
    if not images:
        return None
    poses = []
    for number, _ in images:
        arr = np.asarray(require_key(frames[number], "transform_matrix", source), dtype=np.float64)
        entry = arr[min(TEST_POSE_SUBFRAME, len(arr) - 1)] if arr.ndim == 3 else arr
        poses.append(as_pose(entry, source, f"test frame {number}'s transform_matrix"))
    c2w = np.stack(poses)
    height, width = image_size(images[0][1])
    rgb = cached_rgb_images(
        root, "test_rgb", [p for _, p in images], [p.name for _, p in images], background=WHITE_BACKGROUND
    )
    return ViewSet(
        intrinsics=_blender_intrinsics(meta, source, height, width),
        camera_to_worlds=c2w,
        times=nearest_times(c2w, latent_c2w, latent_times),
        image_paths=rgb,
        mask_paths=None,
    )


def read_e2nerf_synthetic(
    root: Path, theta: Optional[float] = None, color_space: Optional[str] = None, clip_max: float = 1.0
) -> SceneRecord:
    """Read an E2NeRF synthetic scene, computing (once) and caching its EDI latents.

    Args:
        root: the scene folder.
        theta: contrast threshold for EDI (default DEFAULT_THETA).
        color_space: encoding of the pixels (default "linear", as E2NeRF treats them).
        clip_max: EDI latents are clipped to [0, clip_max] in linear intensity.

    Raises:
        FileNotFoundError: a required file or folder is missing.
        ValueError: malformed JSON, or events.pt disagrees with the images (names the file and
            both shapes).
    """
    source = root / TRAIN_TRANSFORMS
    meta = load_json(source)
    frames = list(require_key(meta, "frames", source))
    images = _numbered_images(root / TRAIN_FOLDER, source, frames)
    if not images:
        raise FileNotFoundError(f"{root / TRAIN_FOLDER}: no blurry frames named r_<i>.png")
    height, width = image_size(images[0][1])
    event_maps = cached_events_pt(root / EVENTS_FILE, len(images), height, width, root)
    k = int(event_maps.shape[1]) + 1
    latent_c2w = np.concatenate(
        [_latent_poses(require_key(frames[number], "transform_matrix", source), k, source, number) for number, _ in images]
    )
    originals = [p for _, p in images]
    blurry_rgb = cached_rgb_images(root, "train_rgb", originals, [p.name for p in originals], background=WHITE_BACKGROUND)
    edi = EdiConfig(
        k=k,
        theta=float(theta if theta is not None else DEFAULT_THETA),
        color_space=color_space or DEFAULT_COLOR_SPACE,  # type: ignore[arg-type]
        clip_max=clip_max,
    )
    latents = cached_edi_latents(root, blurry_rgb, event_maps, edi, sources=[root / EVENTS_FILE] + originals)
    blurry_index, latent_index = latent_grid(len(images), k)
    times = uniform_latent_times(len(images), k)
    record = SceneRecord(
        root=root,
        layout="e2nerf-synthetic",
        intrinsics=_blender_intrinsics(meta, source, height, width),
        k=k,
        theta=edi.theta,
        color_space=edi.color_space,
        latent_c2w=latent_c2w,
        latent_times=times,
        blurry_index=blurry_index,
        latent_index=latent_index,
        latent_image_paths=[p for row in latents for p in row],
        blurry_image_paths=blurry_rgb,
        event_maps=event_maps,
        pose_source="given",
        novel=_read_test_views(root, latent_c2w, times),
        notes={"background": "white", "frame_numbers": [number for number, _ in images]},
    )
    record.check()
    return record

"""Reader for E2NeRF's synthetic (Blender-style) scenes.

Folder::

    transform_train.json   camera_angle_x + frames; frame i carries a LIST of sub-frame poses
    transform_test.json    camera_angle_x + frames of the sharp test views (optional)
    train/r_{i}.png        blurry RGBA frame i (i need not be contiguous: E2NeRF uses even i)
    test/r_{i}.png         sharp RGBA test view i (optional)
    events.pt (event.pt)   float tensor [views, 4, H*W] (or [views, 4, H, W]): signed event
                           counts, 4 bins per view

Image r_{i} of train/ goes with frame i of transform_train.json (E2NeRF's own loader pairs
``train/r_{num}.png`` with ``frames[num]``); view v of events.pt is the v-th train image in
numeric order. k = bins + 1 latents per blurry frame.

Which sub-frame poses are the latents: E2NeRF renders 18 or more sub-frames per blurry frame,
10 ms apart; the blurry frame averages sub-frames 0..17, and its event bins span sub-frames
0->5, 5->9, 9->13 and 13->17. A latent sits at each bin boundary, so the 5 latents are
sub-frames 0, 5, 9, 13, 17 (the first at the exposure start, as EDI's latent 0 is). In general,
with m >= 18 sub-frames latent 0 is sub-frame 0 and latent j >= 1 the sub-frame at
1 + 16 j / (k - 1) (rounded); with fewer sub-frames the k latents are evenly spaced from 0 to
m - 1. A frame with a single 4x4 pose gives that pose to all k latents.

Pixels: E2NeRF's synthetic config sets ``white_bkgd = False``, so its loader keeps the stored RGB
and drops alpha (no compositing); so do we, for the blurry and the test images (converted once
and cached as RGB). EDI latents are computed once from those frames and the bins, and cached.
Contrast threshold: 0.2 by default (ours; E2NeRF's 0.3 is for its real data).
The scenes are static and carry no timestamps: exposures are placed back to back on [0, 1] and
each latent at its sub-frame's instant within its exposure (sub-frame index / 17, see
common.latent_times_from_fractions), and each test view gets the time of the training latent
whose camera centre is nearest.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import List, Optional

import numpy as np

from edygs_ns.data.event_maps import cached_edi_latents, cached_events_pt, cached_rgb_images
from edygs_ns.data.layouts.common import (
    E2NERF_EVENT_FILES,
    SceneRecord,
    ViewSet,
    as_pose,
    find_e2nerf_events,
    latent_grid,
    latent_times_from_fractions,
    load_json,
    nearest_times,
    numbered_files,
    require_key,
)
from edygs_ns.io.images import image_size
from edygs_ns.geometry import POSE_SIZE, Intrinsics
from edygs_ns.events.edi import EdiConfig

#: Train camera file.
TRAIN_TRANSFORMS = "transform_train.json"
#: Test camera file.
TEST_TRANSFORMS = "transform_test.json"
#: Event counts file (E2NeRF's README calls it event.pt; either is read, events.pt first).
EVENTS_FILE = E2NERF_EVENT_FILES[0]
#: Folder of blurry training frames.
TRAIN_FOLDER = "train"
#: Folder of sharp test views.
TEST_FOLDER = "test"
#: File names of frames: r_<number>.png.
IMAGE_PATTERN = r"r_(\d+)\.png"
#: Background that transparent pixels are composited on: None, i.e. alpha dropped and the
#: stored RGB kept (E2NeRF's synthetic config has white_bkgd = False).
BACKGROUND = None
#: E2NeRF's convention for long sub-frame lists: the exposure (and bin 0) starts at sub-frame
#: 0; the later bin boundaries sit on the grid 1 + 4 j (5, 9, 13) up to the exposure end,
#: sub-frame 17: latents at 0, 5, 9, 13, 17.
E2NERF_START_SUBFRAME = 0
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
    """An E2NeRF synthetic scene has transform_train.json and events.pt (or event.pt)."""
    return (root / TRAIN_TRANSFORMS).is_file() and find_e2nerf_events(root) is not None


def subframe_indices(m: int, k: int) -> np.ndarray:
    """Indices [k] of the latent poses in a list of m sub-frame poses (see the module docstring).

    m >= 18 (E2NeRF): 0, then round(1 + 16 j / (k - 1)) for j >= 1 (0, 5, 9, 13, 17 for k = 5);
    fewer: k indices evenly spaced over 0..m-1.

    Raises:
        ValueError: m < k.
    """
    if m < k:
        raise ValueError(f"a frame has {m} sub-frame poses, fewer than k={k} latents")
    if m < E2NERF_MIN_SUBFRAMES:
        return np.round(np.linspace(0, m - 1, k)).astype(np.int64)
    indices = np.round(np.linspace(E2NERF_FIRST_SUBFRAME, E2NERF_LAST_SUBFRAME, k)).astype(np.int64)
    indices[0] = E2NERF_START_SUBFRAME
    return indices


def subframe_fractions(m: int, k: int) -> np.ndarray:
    """[k] where each latent sits in its exposure, in [0, 1]: sub-frame index over the last one
    the blur averages (17 for E2NeRF's m >= 18, else m - 1); j / (k - 1) for m == 1."""
    if m <= 1:
        return np.linspace(0.0, 1.0, k)
    last = E2NERF_LAST_SUBFRAME if m >= E2NERF_MIN_SUBFRAMES else m - 1
    return subframe_indices(m, k) / float(last)


def _subframe_count(matrix) -> int:
    """Number of sub-frame poses a frame lists (1 for a single 4x4 pose)."""
    arr = np.asarray(matrix, dtype=np.float64)
    return int(arr.shape[0]) if arr.ndim == 3 else 1


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
    """The sharp test views (alpha dropped as E2NeRF does, cached), or None if the scene has none."""
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
        root, "test_rgb", [p for _, p in images], [p.name for _, p in images], background=BACKGROUND
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
    events = find_e2nerf_events(root) or root / EVENTS_FILE
    source = root / TRAIN_TRANSFORMS
    meta = load_json(source)
    frames = list(require_key(meta, "frames", source))
    images = _numbered_images(root / TRAIN_FOLDER, source, frames)
    if not images:
        raise FileNotFoundError(f"{root / TRAIN_FOLDER}: no blurry frames named r_<i>.png")
    height, width = image_size(images[0][1])
    event_maps = cached_events_pt(events, len(images), height, width, root)
    k = int(event_maps.shape[1]) + 1
    matrices = [require_key(frames[number], "transform_matrix", source) for number, _ in images]
    latent_c2w = np.concatenate([_latent_poses(m, k, source, number) for m, (number, _) in zip(matrices, images)])
    fractions = np.stack([subframe_fractions(_subframe_count(m), k) for m in matrices])
    originals = [p for _, p in images]
    blurry_rgb = cached_rgb_images(root, "train_rgb", originals, [p.name for p in originals], background=BACKGROUND)
    edi = EdiConfig(
        k=k,
        theta=float(theta if theta is not None else DEFAULT_THETA),
        color_space=color_space or DEFAULT_COLOR_SPACE,  # type: ignore[arg-type]
        clip_max=clip_max,
    )
    latents = cached_edi_latents(root, blurry_rgb, event_maps, edi, sources=[events] + originals)
    blurry_index, latent_index = latent_grid(len(images), k)
    times = latent_times_from_fractions(fractions)
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
        notes={"background": "none (alpha dropped, as E2NeRF's white_bkgd = False)",
               "frame_numbers": [number for number, _ in images], "events_file": events.name},
    )
    record.check()
    return record

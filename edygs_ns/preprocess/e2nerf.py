"""E2NeRF scenes, read as the authors' public loader reads them: the one reader behind both
``edygs-process --e2nerf`` and the dataparser's ``e2nerf-synthetic`` / ``e2nerf-real`` layouts.

Synthetic (Blender style)::

    transform_train.json   camera_angle_x + frames; frame i carries a LIST of sub-frame poses
    transform_test.json    camera_angle_x + frames of the sharp test views (optional)
    train/r_{i}.png        blurry RGBA frame i (i need not be contiguous: E2NeRF uses even i)
    test/r_{i}.png         sharp RGBA test view i (optional)
    events.pt (event.pt)   float tensor [views, bins, H*W] or [views, bins, H, W]: signed counts

Real (LLFF style, a DAVIS346)::

    images/000.jpg, 005.jpg, ...   blurry frames, in name order
    poses_bounds.npy               [views * k, 17]: one LLFF row per LATENT, in time order
    events.pt (event.pt)           as above, 4 bins per view

Image r_{i} of train/ goes with frame i of transform_train.json, and view v of the event file is
the v-th image in numeric (synthetic) or name (real) order.

Which sub-frame poses are the synthetic latents: E2NeRF renders 18 or more sub-frames per blurry
frame, 10 ms apart; the blurry frame averages sub-frames 0..17 and its event bins span sub-frames
0->5, 5->9, 9->13 and 13->17, so the 5 latents are sub-frames 0, 5, 9, 13, 17 (latent j >= 1 at
1 + 16 j / (k - 1), rounded). With fewer sub-frames the k latents are evenly spaced; a frame with
one 4x4 pose gives it to every latent. Pixels keep their stored RGB, alpha dropped (E2NeRF's
synthetic config has ``white_bkgd = False``).

Real data (its EDI.py): bins are fixed 25.001 ms windows from the exposure start and EDI uses
Θ = 0.3. poses_bounds.npy is read by :mod:`.llff` (the focal length in hwf is rescaled to the
stored images' width, the principal point is the image centre).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, List, Optional, Sequence, Tuple

import numpy as np

from edygs_ns.geometry import POSE_SIZE, Intrinsics
from edygs_ns.io.files import as_pose, load_json, numbered_files, require_key
from edygs_ns.preprocess import llff

#: E2NeRF's event file: its preprocessing writes events.pt, its README names event.pt.
EVENT_FILES = ("events.pt", "event.pt")
#: Event bins per blurry frame in E2NeRF's data (5 latents).
BINS = 4
#: Synthetic scene files.
TRAIN_TRANSFORMS = "transform_train.json"
TEST_TRANSFORMS = "transform_test.json"
TRAIN_FOLDER = "train"
TEST_FOLDER = "test"
#: File names of synthetic frames: r_<number>.png.
IMAGE_PATTERN = r"r_(\d+)\.png"
#: Synthetic sub-frame convention: bin 0 starts at sub-frame 0, later bin boundaries sit on the
#: grid 1 + 4 j (5, 9, 13) up to the exposure end, sub-frame 17.
START_SUBFRAME = 0
FIRST_SUBFRAME = 1
LAST_SUBFRAME = 17
#: Sub-frame lists at least this long follow E2NeRF's convention.
MIN_SUBFRAMES = LAST_SUBFRAME + 1
#: Which entry of a test frame's pose list is the view (E2NeRF's loader takes entry 1).
TEST_POSE_SUBFRAME = 1
#: Sub-frames are this many µs apart (only sets the nominal exposure length).
SUBFRAME_US = 10_000
#: E2NeRF's Blender scenes are rendered between these depths (its loader's near and far).
BLENDER_DEPTH_RANGE = (2.0, 6.0)
#: Real scene files.
POSES_BOUNDS_FILE = "poses_bounds.npy"
IMAGES_FOLDER = "images"
#: Image suffixes accepted in images/ (compared lower-case).
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
#: Real data: E2NeRF bins events in fixed windows of this many µs from the exposure start.
BIN_US = 25_001
#: Contrast thresholds: E2NeRF's real-data EDI.py, and ours for its synthetic data.
REAL_THETA = 0.3
SYNTHETIC_THETA = 0.2


def find_events_file(root: Path) -> Optional[Path]:
    """The event file of a scene folder (events.pt, else event.pt), or None."""
    for name in EVENT_FILES:
        if (Path(root) / name).is_file():
            return Path(root) / name
    return None


def events_file(root: Path) -> Path:
    """The event file of a scene folder.

    Raises:
        FileNotFoundError: neither events.pt nor event.pt exists.
    """
    found = find_events_file(root)
    if found is None:
        raise FileNotFoundError(f"{root}: E2NeRF event bins not found (looked for {' and '.join(EVENT_FILES)})")
    return found


def is_synthetic(root: Path) -> bool:
    """A synthetic scene has transform_train.json and an event file."""
    return (Path(root) / TRAIN_TRANSFORMS).is_file() and find_events_file(root) is not None


def is_real(root: Path) -> bool:
    """A real scene has poses_bounds.npy, an event file and an images/ folder."""
    root = Path(root)
    return (root / POSES_BOUNDS_FILE).is_file() and find_events_file(root) is not None and (root / IMAGES_FOLDER).is_dir()


def read_event_bins(path: Path, n_views: int, height: int, width: int, bins: Optional[int] = None) -> np.ndarray:
    """An E2NeRF event file as float32 [views, bins, H, W] signed counts.

    Args:
        path: events.pt / event.pt, one tensor [views, bins, H*W] or [views, bins, H, W].
        n_views, height, width: the scene's blurry frames.
        bins: bins per view required (None: any positive number).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a tensor file, or a shape that disagrees with the frames (one line naming
            the file, the shape found and the shapes expected).
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: E2NeRF event bins not found")
    try:
        tensor = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # pickle, zip and torch errors alike: one line naming the file
        raise ValueError(f"{path}: cannot read as a torch tensor file ({type(err).__name__}: {err})") from None
    if not isinstance(tensor, torch.Tensor):
        raise ValueError(f"{path}: expected one tensor of event bins, got a {type(tensor).__name__}")
    shape = tuple(int(s) for s in tensor.shape)
    want = "any" if bins is None else str(bins)
    flat_ok = len(shape) == 3 and shape[2] == height * width
    grid_ok = len(shape) == 4 and shape[2:] == (height, width)
    bins_ok = len(shape) >= 2 and shape[1] >= 1 and (bins is None or shape[1] == bins)
    if not (flat_ok or grid_ok) or shape[0] != n_views or not bins_ok:
        raise ValueError(
            f"{path}: event bins have shape {shape}, expected ({n_views}, {want}, {height * width}) or "
            f"({n_views}, {want}, {height}, {width}) for {n_views} {width}x{height} frames"
        )
    return np.ascontiguousarray(tensor.to(torch.float32).reshape(n_views, shape[1], height, width).numpy())


def merge_bins(bins: np.ndarray, k: int, source: Path) -> np.ndarray:
    """[views, BINS, H, W] counts summed into k - 1 bins [views, k-1, H, W] (k - 1 must divide BINS).

    Raises:
        ValueError: k - 1 does not divide the stored bin count (names the file).
    """
    stored = bins.shape[1]
    if k < 2 or stored % (k - 1) != 0:
        raise ValueError(f"{source}: E2NeRF stores {stored} event bins per frame; k - 1 must divide it, got k={k}")
    n, _, h, w = bins.shape
    return np.ascontiguousarray(bins.reshape(n, k - 1, stored // (k - 1), h, w).sum(axis=2), dtype=np.float32)


# ----------------------------------------------------------------------------------------------
# Synthetic scenes


def subframe_indices(m: int, k: int) -> np.ndarray:
    """Indices [k] of the latent poses in a list of m sub-frame poses (module docstring).

    m >= 18 (E2NeRF): 0, then round(1 + 16 j / (k - 1)) for j >= 1 (0, 5, 9, 13, 17 for k = 5);
    fewer: k indices evenly spaced over 0..m-1.

    Raises:
        ValueError: m < k.
    """
    if m < k:
        raise ValueError(f"a frame has {m} sub-frame poses, fewer than k={k} latents")
    if m < MIN_SUBFRAMES:
        return np.round(np.linspace(0, m - 1, k)).astype(np.int64)
    indices = np.round(np.linspace(FIRST_SUBFRAME, LAST_SUBFRAME, k)).astype(np.int64)
    indices[0] = START_SUBFRAME
    return indices


def subframe_fractions(m: int, k: int) -> np.ndarray:
    """[k] where each latent sits in its exposure, in [0, 1]: sub-frame index over the last one
    the blur averages (17 for E2NeRF's m >= 18, else m - 1); j / (k - 1) for m == 1."""
    if m <= 1:
        return np.linspace(0.0, 1.0, k)
    last = LAST_SUBFRAME if m >= MIN_SUBFRAMES else m - 1
    return subframe_indices(m, k) / float(last)


def blender_intrinsics(meta: Any, source: Path, height: int, width: int) -> Intrinsics:
    """Pinhole camera of a Blender-style JSON (camera_angle_x) for width x height images."""
    focal = 0.5 * width / math.tan(0.5 * float(require_key(meta, "camera_angle_x", source)))
    return Intrinsics(width=width, height=height, fl_x=focal, fl_y=focal, cx=width / 2.0, cy=height / 2.0)


def _numbered_images(folder: Path, source: Path, frames: Sequence[Any]) -> List[Tuple[int, Path]]:
    """(number, path) of r_<number>.png in folder; each number must index a listed frame."""
    images = numbered_files(folder, IMAGE_PATTERN)
    for number, path in images:
        if number >= len(frames):
            raise ValueError(f"{source}: {path.name} has no frame {number} ({len(frames)} frames listed)")
    return images


def _frame_poses(matrix: Any, k: int, source: Path, frame: int) -> Tuple[np.ndarray, np.ndarray]:
    """([k, 4, 4] latent poses, [k] fractions of the exposure) of one frame's transform_matrix."""
    arr = np.asarray(matrix, dtype=np.float64)
    if arr.ndim == 2:
        pose = as_pose(arr, source, f"frame {frame}'s transform_matrix")
        return np.repeat(pose[None], k, axis=0), subframe_fractions(1, k)
    if arr.ndim != 3 or arr.shape[1:] != (POSE_SIZE, POSE_SIZE):
        raise ValueError(f"{source}: frame {frame}'s transform_matrix has shape {arr.shape}, expected [m, 4, 4] or [4, 4]")
    try:
        idx = subframe_indices(arr.shape[0], k)
    except ValueError as err:
        raise ValueError(f"{source}: frame {frame}: {err}") from err
    poses = np.stack([as_pose(arr[i], source, f"frame {frame} sub-pose {i}") for i in idx])
    return poses, subframe_fractions(arr.shape[0], k)


@dataclass
class SyntheticScene:
    """An E2NeRF synthetic scene's training frames and (optional) test views, read and checked.

    Attributes:
        root: the scene folder.
        meta_path: transform_train.json.
        meta: its content.
        numbers: n frame numbers of the training images (r_<number>.png).
        image_paths: the n blurry RGBA images, in number order.
        events_path: the scene's event file.
    """

    root: Path
    meta_path: Path
    meta: Any
    numbers: List[int]
    image_paths: List[Path]
    events_path: Path

    def latent_poses(self, k: int) -> Tuple[np.ndarray, np.ndarray]:
        """([n, k, 4, 4] OpenGL c2w of every latent, [n, k] fractions of the exposure where they sit)."""
        frames = self.meta["frames"]
        pairs = [_frame_poses(require_key(frames[i], "transform_matrix", self.meta_path), k, self.meta_path, i)
                 for i in self.numbers]
        return np.stack([p for p, _ in pairs]), np.stack([f for _, f in pairs])

    def intrinsics(self, height: int, width: int) -> Intrinsics:
        return blender_intrinsics(self.meta, self.meta_path, height, width)

    def test_views(self) -> Optional[Tuple[Any, Path, List[Path], np.ndarray]]:
        """(test meta, its path, sharp images, [V, 4, 4] poses), or None when the scene has none."""
        source = self.root / TEST_TRANSFORMS
        if not source.is_file() or not (self.root / TEST_FOLDER).is_dir():
            return None
        meta = load_json(source)
        frames = list(require_key(meta, "frames", source))
        images = _numbered_images(self.root / TEST_FOLDER, source, frames)
        if not images:
            return None
        poses = []
        for number, _ in images:
            arr = np.asarray(require_key(frames[number], "transform_matrix", source), dtype=np.float64)
            entry = arr[min(TEST_POSE_SUBFRAME, len(arr) - 1)] if arr.ndim == 3 else arr
            poses.append(as_pose(entry, source, f"test frame {number}'s transform_matrix"))
        return meta, source, [p for _, p in images], np.stack(poses)


def read_synthetic(root: Path) -> SyntheticScene:
    """Read (without pixels) an E2NeRF synthetic scene.

    Raises:
        FileNotFoundError: transform_train.json, the training images or the event file missing.
        ValueError: malformed JSON, or an image without a listed frame (named).
    """
    root = Path(root)
    source = root / TRAIN_TRANSFORMS
    meta = load_json(source)
    frames = list(require_key(meta, "frames", source))
    images = _numbered_images(root / TRAIN_FOLDER, source, frames)
    if not images:
        raise FileNotFoundError(f"{root / TRAIN_FOLDER}: no blurry frames named r_<i>.png for the frames of {source}")
    return SyntheticScene(root, source, meta, [n for n, _ in images], [p for _, p in images], events_file(root))


# ----------------------------------------------------------------------------------------------
# Real scenes


@dataclass
class RealScene:
    """An E2NeRF real scene, read and checked.

    Attributes:
        root: the scene folder.
        image_paths: n blurry frames, name order.
        c2w: [n, m, 4, 4] OpenGL camera-to-world of the m latents of each frame.
        intrinsics: pinhole camera at the stored images' size.
        depth_range: (smallest near, largest far) of poses_bounds.npy.
        events_path: the scene's event file.
    """

    root: Path
    image_paths: List[Path]
    c2w: np.ndarray
    intrinsics: Intrinsics
    depth_range: Tuple[float, float]
    events_path: Path

    @property
    def poses_path(self) -> Path:
        return self.root / POSES_BOUNDS_FILE


def real_images(root: Path) -> List[Path]:
    """The blurry frames of a real scene, name order.

    Raises:
        FileNotFoundError: images/ is missing or holds none.
    """
    folder = Path(root) / IMAGES_FOLDER
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES) if folder.is_dir() else []
    if not images:
        raise FileNotFoundError(f"{folder}: no blurry frames ({', '.join(IMAGE_SUFFIXES)})")
    return images


def read_real(root: Path, latents_per_frame: int, height: int, width: int, why: str = "") -> RealScene:
    """Read (without pixels) an E2NeRF real scene whose frames are height x width.

    Args:
        root: the scene folder.
        latents_per_frame: poses_bounds.npy rows per blurry frame.
        height, width: the stored images' size (the hwf focal length is rescaled to it).
        why: where latents_per_frame comes from, for the shape error.

    Raises:
        FileNotFoundError: images/, poses_bounds.npy or the event file missing.
        ValueError: poses_bounds.npy of another shape or with non-finite values (names the file).
    """
    root = Path(root)
    images = real_images(root)
    why = f"{len(images)} images x {latents_per_frame} latents" + (f", {why}" if why else "")
    rows = llff.read_rows(root / POSES_BOUNDS_FILE, len(images) * latents_per_frame, f"one row per latent: {why}")
    return RealScene(
        root=root,
        image_paths=images,
        c2w=llff.rows_to_c2w(rows).reshape(len(images), latents_per_frame, POSE_SIZE, POSE_SIZE),
        intrinsics=llff.rows_intrinsics(rows, height, width),
        depth_range=llff.rows_depth_range(rows),
        events_path=events_file(root),
    )

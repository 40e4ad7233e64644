"""Reader for our processed layout (docs/layouts.md, what ``edygs-process`` writes).

``transforms.json`` lists one frame per latent with its pose, time and indices; event_maps.npy
holds the event bins; sparse_pc.ply the initial points; gt/ (optional) the sharp ground truth
of every latent and the novel views. When the latent poses were estimated (pose_source other
than "given"), the ground truth lives in another world frame: it is moved into the estimated
frame by the Sim(3) (Umeyama) that best maps the ground-truth latent centres onto the
estimated ones, so novel-view cameras can be rendered by the trained model.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from edygs_ns.preprocess.cache import load_event_maps_npy
from edygs_ns.data.layouts.common import GT_ALIGNMENT_SCALE_NOTE, PROCESSED_LAYOUT, SceneRecord, ViewSet
from edygs_ns.io.files import as_pose, load_json, require_files, require_key
from edygs_ns.io.ply import read_ply_points
from edygs_ns.geometry import Intrinsics, align_poses, apply_sim3

#: The scene description file.
TRANSFORMS_FILE = "transforms.json"
#: Event maps file when transforms.json does not name one.
DEFAULT_EVENT_MAPS_FILE = "event_maps.npy"
#: Initial points file when transforms.json does not name one.
DEFAULT_PLY_FILE = "sparse_pc.ply"
#: Ground-truth folder (with its own transforms.json).
GT_FOLDER = "gt"
#: Camera models we accept: undistorted pinhole only.
SUPPORTED_CAMERA_MODELS = ("PINHOLE", "OPENCV", "SIMPLE_PINHOLE")
#: Distortion keys that must be absent or zero.
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
#: Pose sources whose poses share the ground truth's world frame (no alignment needed).
GT_FRAME_POSE_SOURCES = ("given",)
#: Fewest shared latents needed to fit the Sim(3) between ground truth and estimated poses.
MIN_ALIGNMENT_POINTS = 3


def is_processed(root: Path) -> bool:
    """A processed scene has transforms.json and event maps next to it."""
    return (root / TRANSFORMS_FILE).is_file() and (root / DEFAULT_EVENT_MAPS_FILE).is_file()


def _intrinsics(meta: Dict[str, Any], source: Path, fallback: Optional[Intrinsics] = None) -> Intrinsics:
    """Pinhole intrinsics from nerfstudio-style keys (w, h, fl_x, fl_y, cx, cy)."""
    model = meta.get("camera_model", "PINHOLE")
    if model not in SUPPORTED_CAMERA_MODELS:
        raise ValueError(f"{source}: camera_model {model!r} is not supported; use one of {SUPPORTED_CAMERA_MODELS}")
    distorted = [key for key in DISTORTION_KEYS if float(meta.get(key, 0.0)) != 0.0]
    if distorted:
        raise ValueError(f"{source}: lens distortion ({', '.join(distorted)}) is not supported; undistort the images first")
    if fallback is not None and "fl_x" not in meta:
        return fallback
    width = int(require_key(meta, "w", source))
    height = int(require_key(meta, "h", source))
    fx = float(require_key(meta, "fl_x", source))
    return Intrinsics(
        width=width,
        height=height,
        fl_x=fx,
        fl_y=float(meta.get("fl_y", fx)),
        cx=float(meta.get("cx", width / 2.0)),
        cy=float(meta.get("cy", height / 2.0)),
    )


def _frame_key(frame: Dict[str, Any], source: Path, position: int) -> Tuple[int, int]:
    for key in ("blurry_index", "latent_index"):
        if key not in frame:
            raise ValueError(f"{source}: frame {position} lacks {key!r}")
    return int(frame["blurry_index"]), int(frame["latent_index"])


def _blurry_files(meta: Dict[str, Any], frames: List[Dict[str, Any]], root: Path, source: Path) -> List[Path]:
    """The blurry images by blurry index: from the exposure table when present, else from the frames."""
    exposures = meta.get("exposures")
    if exposures and (root / exposures).is_file():
        from edygs_ns.events.exposures import read_exposures

        return [Path(e.file) for e in read_exposures(root / exposures)]
    by_index: Dict[int, Path] = {}
    for position, frame in enumerate(frames):
        b, _ = _frame_key(frame, source, position)
        by_index[b] = root / require_key(frame, "blurry_file_path", source)
    n = max(by_index) + 1
    missing = sorted(set(range(n)) - set(by_index))
    if missing:
        raise ValueError(f"{source}: no frame names the blurry image of exposure(s) {missing[:5]} and no exposure table is given")
    return [by_index[b] for b in range(n)]


def _times(frames: List[Dict[str, Any]], source: Path) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """Normalised times [N] (from 'time', else from 'time_us') and time_us [N] when every frame has it."""
    time_us = np.array([f["time_us"] for f in frames], dtype=np.int64) if all("time_us" in f for f in frames) else None
    if all("time" in f for f in frames):
        times = np.array([f["time"] for f in frames], dtype=np.float64)
    elif time_us is not None:
        span = max(int(time_us.max() - time_us.min()), 1)
        times = (time_us - time_us.min()) / span
    else:
        raise ValueError(f"{source}: frames need 'time' (normalised) or 'time_us'")
    if len(times) > 1 and not np.all(np.diff(times) > 0):
        bad = int(np.flatnonzero(np.diff(times) <= 0)[0])
        raise ValueError(
            f"{source}: latent times must increase with (blurry_index, latent_index); "
            f"frame {bad + 1} has time {times[bad + 1]} after {times[bad]}"
        )
    return times, time_us


def _time_mapper(latent_times: np.ndarray, latent_time_us: Optional[np.ndarray]):
    """A function mapping a ground-truth frame dict to a normalised time on the latents' clock."""

    def to_time(frame: Dict[str, Any]) -> float:
        if latent_time_us is not None and "time_us" in frame and latent_time_us.max() > latent_time_us.min():
            t0, t1 = latent_time_us.min(), latent_time_us.max()
            s0, s1 = latent_times.min(), latent_times.max()
            value = s0 + (float(frame["time_us"]) - t0) * (s1 - s0) / float(t1 - t0)
        else:
            value = float(frame["time"])
        return float(np.clip(value, 0.0, 1.0))

    return to_time


def _read_gt(
    root: Path,
    record: SceneRecord,
    latent_time_us: Optional[np.ndarray],
) -> None:
    """Fill record.gt_* and record.novel from gt/transforms.json (if present)."""
    from nerfstudio.utils.rich_utils import CONSOLE

    source = root / GT_FOLDER / TRANSFORMS_FILE
    if not source.is_file():
        return
    meta = load_json(source)
    gt_root = source.parent
    intrinsics = _intrinsics(meta, source, fallback=record.intrinsics)
    by_key = {}
    for position, frame in enumerate(meta.get("frames", [])):
        by_key[_frame_key(frame, source, position)] = frame
    keys = list(zip(record.blurry_index.tolist(), record.latent_index.tolist()))
    if by_key and all(key in by_key for key in keys):
        frames = [by_key[key] for key in keys]
        record.gt_image_paths = [gt_root / require_key(f, "file_path", source) for f in frames]
        require_files(record.gt_image_paths, source)
        if all("mask_path" in f for f in frames):
            record.gt_mask_paths = [gt_root / f["mask_path"] for f in frames]
            require_files(record.gt_mask_paths, source)
        record.gt_c2w = np.stack([as_pose(require_key(f, "transform_matrix", source), source, "a frame's pose") for f in frames])
    elif by_key:
        CONSOLE.log(f"[yellow]{source}: ground truth does not cover every latent; no per-latent ground truth used")

    to_time = _time_mapper(record.latent_times, latent_time_us)
    novel_frames = meta.get("novel_frames", [])
    if novel_frames:
        images = [gt_root / require_key(f, "file_path", source) for f in novel_frames]
        require_files(images, source)
        masks = [gt_root / f["mask_path"] for f in novel_frames] if all("mask_path" in f for f in novel_frames) else None
        if masks is not None:
            require_files(masks, source)
        covisible = [gt_root / f["covisible_path"] for f in novel_frames] if all("covisible_path" in f for f in novel_frames) else None
        if covisible is not None:
            require_files(covisible, source)
        record.novel = ViewSet(
            intrinsics=intrinsics,
            camera_to_worlds=np.stack(
                [as_pose(require_key(f, "transform_matrix", source), source, "a novel frame's pose") for f in novel_frames]
            ),
            times=np.array([to_time(f) for f in novel_frames], dtype=np.float64),
            image_paths=images,
            mask_paths=masks,
            covisible_paths=covisible,
        )
    if record.pose_source not in GT_FRAME_POSE_SOURCES:
        _align_gt_to_estimate(record, source)


def _align_gt_to_estimate(record: SceneRecord, source: Path) -> None:
    """Move ground-truth poses into the estimated poses' frame by a Sim(3) on camera centres."""
    from nerfstudio.utils.rich_utils import CONSOLE

    if record.gt_c2w is None or len(record.gt_c2w) < MIN_ALIGNMENT_POINTS:
        if record.novel is not None:
            CONSOLE.log(
                f"[yellow]{source}: poses are {record.pose_source!r} but the ground truth has too few latent poses to "
                "align it; novel views are dropped"
            )
            record.novel = None
        return
    record.gt_c2w, sim3 = align_poses(record.gt_c2w, record.latent_c2w)
    if record.novel is not None:
        record.novel.camera_to_worlds = apply_sim3(record.novel.camera_to_worlds, sim3)
    record.notes = dict(record.notes or {}, **{GT_ALIGNMENT_SCALE_NOTE: float(sim3[0])})


def read_processed(root: Path, theta: Optional[float] = None, color_space: Optional[str] = None) -> SceneRecord:
    """Read a processed scene folder.

    Args:
        root: the scene folder.
        theta: overrides the contrast threshold stored in transforms.json when given.
        color_space: overrides the colour encoding stored in transforms.json when given.

    Returns:
        The scene record (latents sorted by exposure, then position in the exposure).

    Raises:
        FileNotFoundError: transforms.json, an image, the event maps or the PLY is missing.
        ValueError: malformed transforms.json or event maps of the wrong shape (names the file).
    """
    source = root / TRANSFORMS_FILE
    meta = load_json(source)
    intrinsics = _intrinsics(meta, source)
    k = int(require_key(meta, "k", source))
    frames = list(require_key(meta, "frames", source))
    if not frames:
        raise ValueError(f"{source}: 'frames' is empty")
    keyed = sorted(((_frame_key(f, source, i), f) for i, f in enumerate(frames)), key=lambda item: item[0])
    keys = [key for key, _ in keyed]
    if len(set(keys)) != len(keys):
        duplicate = next(key for key in keys if keys.count(key) > 1)
        raise ValueError(f"{source}: two frames share (blurry_index, latent_index) = {duplicate}")
    frames = [f for _, f in keyed]
    times, time_us = _times(frames, source)
    blurry_files = _blurry_files(meta, frames, root, source)
    latent_files = [root / require_key(f, "file_path", source) for f in frames]
    require_files(latent_files + blurry_files, source)
    event_maps = load_event_maps_npy(
        root / meta.get("event_maps", DEFAULT_EVENT_MAPS_FILE), len(blurry_files), k, intrinsics.height, intrinsics.width
    )
    points_xyz = points_rgb = None
    ply_name = meta.get("ply_file_path")
    if ply_name is not None or (root / DEFAULT_PLY_FILE).is_file():
        points_xyz, points_rgb = read_ply_points(root / (ply_name or DEFAULT_PLY_FILE))
    record = SceneRecord(
        root=root,
        layout=PROCESSED_LAYOUT,
        intrinsics=intrinsics,
        k=k,
        theta=float(theta if theta is not None else require_key(meta, "theta", source)),
        color_space=str(color_space or meta.get("color_space", "linear")),
        latent_c2w=np.stack([as_pose(require_key(f, "transform_matrix", source), source, "a frame's pose") for f in frames]),
        latent_times=times,
        blurry_index=np.array([key[0] for key in keys], dtype=np.int64),
        latent_index=np.array([key[1] for key in keys], dtype=np.int64),
        latent_image_paths=latent_files,
        blurry_image_paths=blurry_files,
        event_maps=event_maps,
        pose_source=str(meta.get("pose_source", "given")),
        points_xyz=points_xyz,
        points_rgb=points_rgb,
    )
    _read_gt(root, record, time_us)
    record.check()
    return record

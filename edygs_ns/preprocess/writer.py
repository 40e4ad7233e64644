"""Write the processed scene layout of docs/layouts.md.

``transforms.json`` is written last, under a temporary name in the work folder and moved into
place, so a scene folder either has a complete, fully posed transforms.json or none at all.
The images and the event maps produced by earlier steps in the work folder are hard-linked
into the scene (copied where links are not possible), or undistorted when the camera has lens
distortion (OPENCV model).
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np

from edygs_ns.events.exposures import Exposure, write_exposures
from edygs_ns.preprocess.colmap import CameraEstimate
from edygs_ns.geometry import Intrinsics, interpolate_poses
from edygs_ns.io.images import read_rgb_uint8, write_rgb_png
from edygs_ns.io.ply import write_ply_points

#: Folder names and files of the processed layout.
LATENTS_DIR = "latents"
BLURRY_DIR = "blurry"
GT_DIR = "gt"
TRANSFORMS_NAME = "transforms.json"
EVENT_MAPS_NAME = "event_maps.npy"
EXPOSURES_NAME = "exposures.csv"
PLY_NAME = "sparse_pc.ply"
REPORT_NAME = "process_report.json"
#: Every entry of the scene folder the writer produces.
SCENE_ENTRIES = (TRANSFORMS_NAME, LATENTS_DIR, BLURRY_DIR, EVENT_MAPS_NAME, EXPOSURES_NAME, PLY_NAME, REPORT_NAME, GT_DIR)
#: Camera model written to transforms.json (images are undistorted when needed).
OUTPUT_CAMERA_MODEL = "PINHOLE"
#: OpenCV puts pixel centres at integers, COLMAP and nerfstudio at integer + 0.5.
PIXEL_CENTRE_OFFSET = 0.5
#: getOptimalNewCameraMatrix's alpha: 0 keeps only valid pixels after undistortion.
UNDISTORT_ALPHA = 0.0
#: Image suffixes in gt/ that are resized with the scene when downscaling.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
#: Keys of a transforms.json holding pixel-unit intrinsics, rescaled with the images.
PIXEL_KEYS_X = ("w", "fl_x", "cx")
PIXEL_KEYS_Y = ("h", "fl_y", "cy")


def latent_name(blurry_index: int, latent_index: int) -> str:
    """File name of latent j of blurry frame i: ``NNNN_J.png``."""
    return f"{blurry_index:04d}_{latent_index}.png"


def blurry_name(blurry_index: int) -> str:
    """File name of blurry frame i: ``NNNN.png``."""
    return f"{blurry_index:04d}.png"


def complete_poses(c2w: np.ndarray, registered: np.ndarray, times_us: np.ndarray) -> np.ndarray:
    """Fill the poses of unregistered latents by interpolating registered ones in time.

    Args:
        c2w: [N, 4, 4] poses (anything where unregistered).
        registered: [N] bool, at least one True.
        times_us: [N] latent times, µs.

    Returns:
        [N, 4, 4] float64: registered poses unchanged; the others slerped/lerped between the
        nearest registered latents before and after (held constant past either end).
    """
    out = np.array(c2w, dtype=np.float64)
    if registered.all():
        return out
    known = np.flatnonzero(registered)
    order = known[np.argsort(times_us[known], kind="stable")]
    times, first = np.unique(times_us[order], return_index=True)
    missing = np.flatnonzero(~registered)
    out[missing] = interpolate_poses(times, out[order[first]], times_us[missing])
    return out


def random_points_from_views(
    image_paths: Sequence[Path],
    c2w: np.ndarray,
    intrinsics: Intrinsics,
    depth_range: Tuple[float, float],
    n_points: int,
    rng: np.random.Generator,
) -> Tuple[np.ndarray, np.ndarray]:
    """Random initial points: back-projected random pixels of random views at random depths.

    Each point takes the colour of the pixel it was cast through, so the cloud starts with the
    scene's colours where the depth happens to be right.

    Args:
        image_paths: [N] view images (RGB PNG), one per pose.
        c2w: [N, 4, 4] camera-to-world (OpenGL axes).
        intrinsics: pinhole camera of the images.
        depth_range: (near, far) depth along the viewing axis, world units, uniform between.
        n_points: how many points.
        rng: random generator.

    Returns:
        ([P, 3] float64 xyz, [P, 3] uint8 rgb).
    """
    view = rng.integers(0, len(image_paths), n_points)
    u = rng.uniform(0.0, intrinsics.width, n_points)
    v = rng.uniform(0.0, intrinsics.height, n_points)
    depth = rng.uniform(depth_range[0], depth_range[1], n_points)
    cam = np.stack([(u - intrinsics.cx) / intrinsics.fl_x * depth, -(v - intrinsics.cy) / intrinsics.fl_y * depth, -depth], 1)
    poses = np.asarray(c2w, dtype=np.float64)[view]
    xyz = np.einsum("nij,nj->ni", poses[:, :3, :3], cam) + poses[:, :3, 3]
    rgb = np.zeros((n_points, 3), dtype=np.uint8)
    rows = np.minimum(v.astype(np.int64), intrinsics.height - 1)
    cols = np.minimum(u.astype(np.int64), intrinsics.width - 1)
    for i in np.unique(view):
        chosen = view == i
        rgb[chosen] = read_rgb_uint8(image_paths[i])[rows[chosen], cols[chosen]]
    return xyz, rgb


@dataclass
class Undistorter:
    """Remaps distorted images (OPENCV camera) to a pinhole camera of the same size.

    Attributes:
        map_x: [H, W] float32 source column of every output pixel (OpenCV pixel convention).
        map_y: [H, W] float32 source row.
        intrinsics: the pinhole camera of the undistorted images.
    """

    map_x: np.ndarray
    map_y: np.ndarray
    intrinsics: Intrinsics

    @classmethod
    def from_camera(cls, camera: CameraEstimate) -> "Undistorter":
        """Maps that undistort images of ``camera`` (keeping only valid pixels)."""
        k_cv = camera.matrix()
        k_cv[:2, 2] -= PIXEL_CENTRE_OFFSET
        size = (camera.width, camera.height)
        new_k, _ = cv2.getOptimalNewCameraMatrix(k_cv, camera.distortion(), size, UNDISTORT_ALPHA, size)
        map_x, map_y = cv2.initUndistortRectifyMap(k_cv, camera.distortion(), None, new_k, size, cv2.CV_32FC1)
        intrinsics = Intrinsics(
            camera.width, camera.height, float(new_k[0, 0]), float(new_k[1, 1]),
            float(new_k[0, 2]) + PIXEL_CENTRE_OFFSET, float(new_k[1, 2]) + PIXEL_CENTRE_OFFSET,
        )
        return cls(map_x, map_y, intrinsics)

    def apply(self, image: np.ndarray) -> np.ndarray:
        """Undistort [H, W] or [H, W, C] (any dtype cv2.remap takes; bilinear)."""
        return cv2.remap(image, self.map_x, self.map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def copy_ground_truth(
    src: Path,
    dst: Path,
    frame_map: Dict[int, int],
    size: Tuple[int, int],
    clip_us: Tuple[int, int],
) -> None:
    """Copy a raw capture's gt/ folder, matched to the processed frames.

    The copy is plain when nothing changes; otherwise gt/transforms.json keeps only the latent
    frames of selected blurry frames (``blurry_index`` renumbered like the processed frames,
    ``source_blurry_index`` keeps the raw number), ``time`` is re-normalised over the processed
    clip, and when the processed frames are smaller every image is resized (masks nearest) and
    the intrinsics are rescaled.

    Args:
        src: the raw gt/ folder.
        dst: the scene's gt/ folder (must not exist).
        frame_map: raw frame number -> processed blurry index.
        size: (height, width) of the processed frames.
        clip_us: (first, last) latent time of the processed clip, µs.
    """
    shutil.copytree(src, dst)
    path = dst / TRANSFORMS_NAME
    if not path.is_file():
        return
    meta = json.loads(path.read_text())
    height, width = size
    resize = ("w" in meta and int(meta["w"]) != width) or ("h" in meta and int(meta["h"]) != height)
    if resize:
        sx, sy = width / float(meta["w"]), height / float(meta["h"])
        for key in PIXEL_KEYS_X:
            if key in meta:
                meta[key] = meta[key] * sx
        for key in PIXEL_KEYS_Y:
            if key in meta:
                meta[key] = meta[key] * sy
        meta["w"], meta["h"] = width, height
        for image_path in sorted(dst.rglob("*")):
            if image_path.suffix.lower() in IMAGE_SUFFIXES:
                image = cv2.imread(str(image_path), cv2.IMREAD_UNCHANGED)
                nearest = "mask" in image_path.parent.name
                interpolation = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA
                cv2.imwrite(str(image_path), cv2.resize(image, (width, height), interpolation=interpolation))
    span = max(clip_us[1] - clip_us[0], 1)
    kept = []
    for frame in meta.get("frames", []):
        raw = int(frame.get("blurry_index", -1))
        if raw not in frame_map:
            continue
        frame = dict(frame, blurry_index=frame_map[raw], source_blurry_index=raw)
        kept.append(frame)
    meta["frames"] = kept
    for frame in kept + list(meta.get("novel_frames", [])):
        if "time_us" in frame:
            frame["time"] = (int(frame["time_us"]) - clip_us[0]) / span
    path.write_text(json.dumps(meta, indent=2))


@dataclass
class SceneContent:
    """Everything the processed scene is made of.

    Attributes:
        blurry: [n] blurry frame PNGs (work folder).
        latents: [n][k] latent PNGs (work folder).
        event_maps: the [n, k-1, H, W] float32 .npy (work folder).
        exposures: [n] exposures (µs); rewritten with frame = processed index.
        times_us: [n, k] int64 latent times.
        c2w: [n, k, 4, 4] complete camera-to-world poses (OpenGL axes).
        intrinsics: pinhole camera of the latents as stored in the work folder.
        distorted_camera: the OPENCV camera when the images must be undistorted, else None.
        points_xyz: [P, 3] initial points (world frame of c2w).
        points_rgb: [P, 3] uint8 colours.
        k: latents per blurry frame.
        theta: event threshold used by EDI.
        color_space: pixel encoding ("linear" or "srgb").
        pose_source: "colmap" or "given".
        gt_dir: raw gt/ folder to copy, or None.
        gt_frame_map: raw frame number -> processed blurry index.
    """

    blurry: List[Path]
    latents: List[List[Path]]
    event_maps: Path
    exposures: List[Exposure]
    times_us: np.ndarray
    c2w: np.ndarray
    intrinsics: Intrinsics
    distorted_camera: Optional[CameraEstimate]
    points_xyz: np.ndarray
    points_rgb: np.ndarray
    k: int
    theta: float
    color_space: str
    pose_source: str
    gt_dir: Optional[Path] = None
    gt_frame_map: Optional[Dict[int, int]] = None


def _place_images(sources: Sequence[Path], targets: Sequence[Path], undistort: Optional[Undistorter]) -> None:
    for src, dst in zip(sources, targets):
        if undistort is None:
            _link_or_copy(src, dst)
        else:
            write_rgb_png(dst, undistort.apply(read_rgb_uint8(src)))


def _place_event_maps(src: Path, dst: Path, undistort: Optional[Undistorter]) -> None:
    if undistort is None:
        _link_or_copy(src, dst)
        return
    maps = np.load(src, mmap_mode="r")
    out = np.lib.format.open_memmap(dst, mode="w+", dtype=np.float32, shape=maps.shape)
    for i in range(maps.shape[0]):
        for j in range(maps.shape[1]):
            out[i, j] = undistort.apply(np.ascontiguousarray(maps[i, j]))
    out.flush()
    del out


def transforms_dict(content: SceneContent, intrinsics: Intrinsics) -> Dict[str, object]:
    """The transforms.json of docs/layouts.md for the scene."""
    t0, t1 = int(content.times_us.min()), int(content.times_us.max())
    span = max(t1 - t0, 1)
    frames = []
    for i in range(len(content.exposures)):
        for j in range(content.k):
            frames.append({
                "file_path": f"{LATENTS_DIR}/{latent_name(i, j)}",
                "transform_matrix": content.c2w[i, j].tolist(),
                "time": (int(content.times_us[i, j]) - t0) / span,
                "time_us": int(content.times_us[i, j]),
                "blurry_index": i,
                "latent_index": j,
                "blurry_file_path": f"{BLURRY_DIR}/{blurry_name(i)}",
            })
    return {
        "w": intrinsics.width, "h": intrinsics.height,
        "fl_x": intrinsics.fl_x, "fl_y": intrinsics.fl_y, "cx": intrinsics.cx, "cy": intrinsics.cy,
        "camera_model": OUTPUT_CAMERA_MODEL,
        "k": content.k, "theta": content.theta, "color_space": content.color_space,
        "event_maps": EVENT_MAPS_NAME, "ply_file_path": PLY_NAME, "exposures": EXPOSURES_NAME,
        "pose_source": content.pose_source,
        "frames": frames,
    }


def write_processed_scene(scene: Path, content: SceneContent, work_dir: Path) -> Intrinsics:
    """Write the processed layout into ``scene`` (its own entries must not exist yet).

    Args:
        scene: the output folder.
        content: what to write.
        work_dir: a folder on the same file system for the temporary transforms.json.

    Returns:
        The intrinsics written (undistorted when the camera was OPENCV).
    """
    undistort = Undistorter.from_camera(content.distorted_camera) if content.distorted_camera is not None else None
    intrinsics = undistort.intrinsics if undistort is not None else content.intrinsics
    n, k = len(content.exposures), content.k
    (scene / LATENTS_DIR).mkdir(parents=True)
    (scene / BLURRY_DIR).mkdir(parents=True)
    _place_images(
        [p for row in content.latents for p in row],
        [scene / LATENTS_DIR / latent_name(i, j) for i in range(n) for j in range(k)],
        undistort,
    )
    blurry_targets = [scene / BLURRY_DIR / blurry_name(i) for i in range(n)]
    _place_images(content.blurry, blurry_targets, undistort)
    _place_event_maps(content.event_maps, scene / EVENT_MAPS_NAME, undistort)
    rows = [Exposure(frame=i, start_us=e.start_us, end_us=e.end_us, file=blurry_targets[i]) for i, e in enumerate(content.exposures)]
    write_exposures(scene / EXPOSURES_NAME, rows, relative_to=scene)
    write_ply_points(scene / PLY_NAME, content.points_xyz, content.points_rgb)
    if content.gt_dir is not None:
        copy_ground_truth(
            content.gt_dir, scene / GT_DIR, content.gt_frame_map or {},
            (intrinsics.height, intrinsics.width), (int(content.times_us.min()), int(content.times_us.max())),
        )
    tmp = work_dir / (TRANSFORMS_NAME + ".partial")
    tmp.write_text(json.dumps(transforms_dict(content, intrinsics), indent=2))
    os.replace(tmp, scene / TRANSFORMS_NAME)
    return intrinsics

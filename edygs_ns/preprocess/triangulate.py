"""Initial points at given poses: the EDI latents triangulated with every pose held fixed (pycolmap).

With ``--poses given`` nothing estimates structure, and Gaussians started from random points
explain the training views with floaters near the cameras. Here the latents go through the same
SIFT extraction and sequential matching as the COLMAP route (``--colmap.*`` settings), with the
given pinhole intrinsics fixed; a reconstruction is built from the database's camera, rig, frames
and images posed at the given poses, and COLMAP's point triangulator (``triangulate_points``,
which never moves a pose and here never refines the intrinsics) fills it with points.

Conventions: the given poses are camera-to-world in OpenGL axes (x right, y up, z back), as in
transforms.json; COLMAP wants world-to-camera in OpenCV axes (x right, y down, z forward). The
world frame is shared, so the triangulated points are in the frame of the given poses, the frame
the writer puts in transforms.json and sparse_pc.ply. Pixel centres are at +0.5 in both.

When triangulation gives too few points (or matching finds no pairs) the caller's random points
are used instead, with a one-line warning that says why.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable, Dict, Literal, Optional, Sequence, Tuple

import numpy as np
from nerfstudio.utils.rich_utils import CONSOLE

from edygs_ns.geometry import Intrinsics, c2w_opengl_to_colmap_w2c
from edygs_ns.preprocess.cache import MANIFEST_NAME, CacheFolder
from edygs_ns.preprocess.colmap import COLMAP_LOG_LEVEL, ColmapConfig, _extract, _match

#: Where the given-pose initial points come from: triangulated from the latents, or random.
GivenPoints = Literal["triangulated", "random"]
#: Largest change of a given pose (entries of the [3, 4] world-to-camera) accepted after triangulation.
POSE_TOLERANCE = 1e-6
#: Scratch files inside the triangulation work folder.
DATABASE_NAME = "database.db"
MODEL_DIR = "model"


class TriangulationError(RuntimeError):
    """Triangulation at the given poses gave no usable point cloud; the message says why (one line)."""


@dataclass
class TriangulationConfig:
    """Triangulating the initial points at given poses (features and matching follow --colmap.*)."""

    min_points: int = 100
    """Fewer triangulated points than this: start from random points instead (with a warning)."""
    min_angle_deg: float = 1.5
    """Smallest triangulation angle of a point, degrees (COLMAP's default); larger keeps fewer, more accurate points."""
    max_reprojection_error_px: float = 4.0
    """Points with a larger reprojection error (pixels) are dropped (COLMAP's default)."""


@dataclass
class TriangulatedPoints:
    """Points triangulated at fixed poses.

    Attributes:
        xyz: [P, 3] float64 positions (world frame of the given poses).
        rgb: [P, 3] uint8 colours (mean of the latents' pixels that observe them).
        mean_reprojection_error: pixels.
        mean_track_length: latents observing a point, on average.
        num_pairs: latent pairs with verified matches.
    """

    xyz: np.ndarray
    rgb: np.ndarray
    mean_reprojection_error: float
    mean_track_length: float
    num_pairs: int

    def summary(self) -> str:
        """One line: how many points, how well they fit, from how many pairs."""
        return (f"{len(self.xyz):,} points triangulated at the given poses (mean reprojection error "
                f"{self.mean_reprojection_error:.2f} px, track length {self.mean_track_length:.1f}, "
                f"{self.num_pairs} matched latent pairs)")


@dataclass
class InitialPoints:
    """The initial point cloud chosen for given poses, and how it came about.

    Attributes:
        xyz: [P, 3] float64.
        rgb: [P, 3] uint8.
        source: "triangulated" or "random".
        summary: one line for the step's summary.
        fallback_reason: why random points were used although triangulation was asked for, else None.
        triangulated: the triangulation's numbers when it succeeded, else None.
    """

    xyz: np.ndarray
    rgb: np.ndarray
    source: GivenPoints
    summary: str
    fallback_reason: Optional[str] = None
    triangulated: Optional[Dict[str, float]] = None

    def report(self) -> Dict[str, Any]:
        """JSON-ready description for process_report.json."""
        return {"source": self.source, "num_points": int(len(self.xyz)), "fallback_reason": self.fallback_reason,
                "triangulation": self.triangulated}


def _last_line(err: BaseException) -> str:
    """The last line of an exception's message (COLMAP's carry a check trace before it), or its type."""
    lines = str(err).strip().splitlines()
    return lines[-1] if lines else type(err).__name__


def _rigid(w2c: np.ndarray) -> Any:
    import pycolmap

    return pycolmap.Rigid3d(pycolmap.Rotation3d(np.ascontiguousarray(w2c[:3, :3])), np.ascontiguousarray(w2c[:3, 3]))


def _posed_reconstruction(database: Path, w2c: Dict[str, np.ndarray]) -> Any:
    """A reconstruction of the database's camera, rig, frames and images, every frame at its given pose."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        cameras, rigs, frames, images = db.read_all_cameras(), db.read_all_rigs(), db.read_all_frames(), db.read_all_images()
    finally:
        db.close()
    reconstruction = pycolmap.Reconstruction()
    for camera in cameras:
        reconstruction.add_camera(camera)
    for rig in rigs:
        reconstruction.add_rig(rig)
    image_of_frame = {image.frame_id: image for image in images}
    for frame in frames:
        frame.rig_from_world = _rigid(w2c[image_of_frame[frame.frame_id].name])  # one camera per rig: rig = camera
        reconstruction.add_frame(frame)
    for image in images:
        reconstruction.add_image(image)
    for frame in frames:
        reconstruction.register_frame(frame.frame_id)
    return reconstruction


def _verified_pairs(database: Path) -> Tuple[int, int]:
    """(latent pairs with inlier matches, SIFT features over all latents) in the database."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        _, geometries = db.read_two_view_geometries()
        return sum(1 for g in geometries if len(g.inlier_matches) > 0), int(db.num_keypoints())
    finally:
        db.close()


def triangulate_at_poses(
    image_dir: Path,
    names: Sequence[str],
    c2w: np.ndarray,
    intrinsics: Intrinsics,
    work_dir: Path,
    colmap: ColmapConfig,
    config: TriangulationConfig,
) -> TriangulatedPoints:
    """Triangulate points from the images at fixed poses and intrinsics.

    Args:
        image_dir: folder holding the images (the latents).
        names: N image names in ``image_dir``, in time order (sequential matching pairs them so).
        c2w: [N, 4, 4] camera-to-world, OpenGL axes, one per name.
        intrinsics: the shared pinhole camera (pixels, pixel centres at +0.5).
        work_dir: scratch folder for the database and the model (replaced).
        colmap: feature extraction and matching settings (camera model and calibration are ignored).
        config: triangulation settings.

    Returns:
        The points, in the world frame of ``c2w``.

    Raises:
        TriangulationError: COLMAP failed, no latent pair matched, too few points, or COLMAP moved a pose.
    """
    import pycolmap

    c2w = np.asarray(c2w, dtype=np.float64).reshape(-1, 4, 4)
    if len(c2w) != len(names):
        raise ValueError(f"triangulate_at_poses: {len(names)} images but {len(c2w)} poses")
    pycolmap.logging.minloglevel = COLMAP_LOG_LEVEL
    if work_dir.exists():
        shutil.rmtree(work_dir)
    (work_dir / MODEL_DIR).mkdir(parents=True)
    database = work_dir / DATABASE_NAME
    params = ",".join(f"{v:.10g}" for v in (intrinsics.fl_x, intrinsics.fl_y, intrinsics.cx, intrinsics.cy))
    features = replace(colmap, camera_model="PINHOLE", camera_params=params)
    try:
        _extract(database, image_dir, names, features)
        _match(database, features)
    except RuntimeError as err:  # pycolmap's own failures; the caller falls back to random points
        raise TriangulationError(f"COLMAP failed on the latents in {image_dir}: {_last_line(err)}") from err
    pairs, keypoints = _verified_pairs(database)
    if pairs == 0:
        raise TriangulationError(f"no pair of latents matched ({keypoints:,} SIFT features over {len(names)} latents)")

    w2c = {name: c2w_opengl_to_colmap_w2c(pose) for name, pose in zip(names, c2w)}
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = colmap.num_threads
    options.random_seed = colmap.random_seed
    options.extract_colors = True
    options.triangulation.min_angle = config.min_angle_deg
    options.mapper.filter_min_tri_angle = config.min_angle_deg
    options.mapper.filter_max_reproj_error = config.max_reprojection_error_px
    try:
        model = pycolmap.triangulate_points(
            _posed_reconstruction(database, w2c), database, image_dir, work_dir / MODEL_DIR,
            options=options, refine_intrinsics=False,
        )
    except RuntimeError as err:
        raise TriangulationError(f"COLMAP's triangulation failed in {work_dir}: {_last_line(err)}") from err
    for image in model.images.values():
        moved = np.abs(np.asarray(image.cam_from_world().matrix()) - w2c[image.name]).max()
        if moved > POSE_TOLERANCE:
            raise TriangulationError(f"COLMAP moved the given pose of {image.name} by {moved:.2g}")
    points = list(model.points3D.values())
    xyz = np.array([p.xyz for p in points], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in points], dtype=np.uint8).reshape(-1, 3)
    if len(xyz) < config.min_points:
        raise TriangulationError(
            f"only {len(xyz)} point{'' if len(xyz) == 1 else 's'} triangulated from {pairs} matched latent pairs "
            f"(fewer than --triangulation.min-points {config.min_points})"
        )
    return TriangulatedPoints(
        xyz=xyz, rgb=rgb, mean_reprojection_error=float(model.compute_mean_reprojection_error()),
        mean_track_length=float(model.compute_mean_track_length()), num_pairs=pairs,
    )


def initial_points_at_poses(
    mode: GivenPoints,
    image_dir: Path,
    names: Sequence[str],
    c2w: np.ndarray,
    intrinsics: Intrinsics,
    work_dir: Path,
    colmap: ColmapConfig,
    config: TriangulationConfig,
    random_points: Callable[[], Tuple[np.ndarray, np.ndarray, str]],
) -> InitialPoints:
    """The initial points for given poses: triangulated, or random (asked for, or as a fallback with a warning).

    Args:
        mode: "triangulated" (random only when triangulation fails) or "random".
        image_dir, names, c2w, intrinsics, work_dir, colmap, config: as :func:`triangulate_at_poses`.
        random_points: draws the random cloud: () -> (xyz, rgb, one-line description).
    """
    if mode == "triangulated":
        try:
            tri = triangulate_at_poses(image_dir, names, c2w, intrinsics, work_dir, colmap, config)
        except TriangulationError as err:
            reason = str(err)
        else:
            numbers = {"num_points": int(len(tri.xyz)), "mean_reprojection_error_px": tri.mean_reprojection_error,
                       "mean_track_length": tri.mean_track_length, "matched_pairs": tri.num_pairs}
            return InitialPoints(tri.xyz, tri.rgb, "triangulated", tri.summary(), triangulated=numbers)
        xyz, rgb, description = random_points()
        CONSOLE.print(f"[yellow]warning[/]: no triangulated initial points: {reason}; starting from {description} "
                      "instead", soft_wrap=True)
        return InitialPoints(xyz, rgb, "random", f"{description} (triangulation failed: {reason})", fallback_reason=reason)
    xyz, rgb, description = random_points()
    return InitialPoints(xyz, rgb, "random", description)


#: Cache kind (under <scene>/edygs_cache/) of the points triangulated for a layout read directly.
POINTS_CACHE_KIND = "initial_points"
POINTS_FILE = "points.npz"


def cached_points_at_poses(
    scene_root: Path,
    latent_paths: Sequence[Path],
    c2w: np.ndarray,
    intrinsics: Intrinsics,
    colmap: Optional[ColmapConfig] = None,
    config: Optional[TriangulationConfig] = None,
) -> Tuple[Optional[TriangulatedPoints], str]:
    """Points triangulated from a scene's latents at their given poses, computed once and cached.

    For the layouts the dataparser reads directly (E2NeRF, EvDeblurNeRF): the cache folder is keyed
    on the latents (name, size, mtime), the poses, the intrinsics and the settings; a failure is
    cached too, so the reason is reported again without re-running COLMAP.

    Args:
        scene_root: the scene folder (the cache goes under its edygs_cache/).
        latent_paths: N latent images, all in one folder, in time order.
        c2w: [N, 4, 4] OpenGL camera-to-world of the latents.
        intrinsics: their pinhole camera.
        colmap: feature and matching settings (default: edygs-process's defaults).
        config: triangulation settings (default: edygs-process's defaults).

    Returns:
        (points, one-line summary) on success; (None, the reason in one line) when triangulation
        gave no usable cloud.
    """
    colmap = colmap if colmap is not None else ColmapConfig()
    config = config if config is not None else TriangulationConfig()
    paths = [Path(p) for p in latent_paths]
    folders = {p.parent for p in paths}
    if len(folders) != 1:
        raise ValueError(f"cached_points_at_poses: the latents must share one folder, found {len(folders)}")
    c2w = np.asarray(c2w, dtype=np.float64).reshape(-1, 4, 4)
    params = json.loads(json.dumps({
        "poses_sha1": hashlib.sha1(np.ascontiguousarray(c2w).tobytes()).hexdigest(),
        "intrinsics": asdict(intrinsics), "colmap": asdict(colmap), "triangulation": asdict(config),
    }, default=str))
    cache = CacheFolder(scene_root, POINTS_CACHE_KIND, params, paths)
    stored = cache.path / POINTS_FILE
    if cache.is_complete():
        manifest = json.loads((cache.path / MANIFEST_NAME).read_text())
        if manifest.get("reason") is not None:
            return None, str(manifest["reason"])
        if stored.is_file():
            with np.load(stored, allow_pickle=False) as data:
                found = TriangulatedPoints(data["xyz"], data["rgb"], float(data["error"]), float(data["track"]),
                                           int(data["pairs"]))
            return found, found.summary()
    cache.begin()
    try:
        points = triangulate_at_poses(folders.pop(), [p.name for p in paths], c2w, intrinsics, cache.path / "work",
                                      colmap, config)
    except TriangulationError as err:
        shutil.rmtree(cache.path / "work", ignore_errors=True)
        cache.finish({"reason": str(err)})
        return None, str(err)
    shutil.rmtree(cache.path / "work", ignore_errors=True)
    np.savez(stored, xyz=points.xyz, rgb=points.rgb, error=points.mean_reprojection_error,
             track=points.mean_track_length, pairs=points.num_pairs)
    cache.finish({"summary": points.summary(), "reason": None})
    return points, points.summary()

"""COLMAP through pycolmap on the latent frames: SIFT, sequential matching, incremental mapping.

Small latents (event cameras' frames, 128-346 px wide) are upsampled by a whole factor first
(``feature_resolution``): SIFT then places its features to a fraction of a latent pixel, and the
poses come out 2.5-5 times closer to the truth on the suite's scenes (docs/experiments.md).

Runs on the CPU. One camera is shared by every latent (``CameraMode.SINGLE``): PINHOLE by
default, or OPENCV (k1, k2, p1, p2) when the lens distorts; the writer then undistorts the
latents, blurry frames and event maps with the estimated parameters. Latent names sort in time
order (``NNNN_J.png``), which is the order COLMAP's sequential matcher pairs them in.

COLMAP's poses are world-to-camera in OpenCV axes (x right, y down, z forward); the result
holds camera-to-world in OpenGL axes (x right, y up, z back), the layout's convention, with
the sparse points in the same world frame. Only the largest reconstruction is kept; the mover test
(``colmap_movers``) may then replace it by a map made without a group of points that moves with an
object.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Sequence, Tuple

import numpy as np

from edygs_ns.geometry import Intrinsics, colmap_w2c_to_c2w_opengl
from edygs_ns.io.images import image_size
from edygs_ns.preprocess.colmap_movers import MoverTest, largest_model, remap_without_movers
from edygs_ns.preprocess.steps import progress_bar

#: glog level of COLMAP's own log lines shown (0 info, 1 warning, 2 error).
COLMAP_LOG_LEVEL = 2
#: OPENCV distortion parameters, in COLMAP's order after fx, fy, cx, cy.
OPENCV_DISTORTION = ("k1", "k2", "p1", "p2")
#: File names of the saved result inside the COLMAP work folder.
RESULT_ARRAYS = "result.npz"
RESULT_JSON = "result.json"
#: Images registered by the mapper's initial pair.
INITIAL_PAIR = 2
#: Relative difference of fx and fy below which a calibration counts as square-pixelled.
SQUARE_PIXEL_TOLERANCE = 1e-3
#: Reconstruction id COLMAP gives the first camera in a fresh database.
FIRST_CAMERA_ID = 1
#: Largest factor the latents are upsampled by for COLMAP (ColmapConfig.feature_resolution).
MAX_UPSAMPLE = 4
#: Leading COLMAP camera parameters that are in pixels (focal lengths, principal point), per model.
PIXEL_PARAMS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "OPENCV": 4}
#: Folder of the upsampled latents inside the COLMAP work folder.
UPSAMPLED_DIR = "upsampled"
#: Scratch folder of the mover test inside the COLMAP work folder.
MOVER_TEST_DIR = "mover_test"


@dataclass
class ColmapConfig:
    """COLMAP settings (pycolmap, CPU)."""

    camera_model: Literal["PINHOLE", "SIMPLE_PINHOLE", "OPENCV"] = "SIMPLE_PINHOLE"
    """One shared camera: SIMPLE_PINHOLE (one focal length, square pixels: the default, since event
    cameras and their APS frames have square pixels and a separate fy let COLMAP drift to a wrong
    aspect on small captures), PINHOLE (fx, fy, cx, cy), or OPENCV
    (adds k1, k2, p1, p2) when the lens distorts; OPENCV makes edygs-process undistort the
    latents, blurry frames and event maps with the estimated parameters."""
    camera_params: Optional[str] = None
    """Known intrinsics as COLMAP reads them for the model, e.g. "fx,fy,cx,cy" for PINHOLE (pixels,
    principal point with pixel centres at +0.5). None: COLMAP starts from 1.2 x the larger image side."""
    refine_focal_length: bool = True
    """Let bundle adjustment refine the focal length (and distortion); False keeps camera_params fixed."""
    use_calibration: bool = True
    """When the capture's intrinsics are known (--intrinsics, camera.json beside the exposure table, or
    an E2NeRF / EvDeblurNeRF scene's own) and camera_params is not set: give them to COLMAP and keep
    them fixed. Small, narrow-baseline captures do not constrain the focal length: on the built-in
    scene COLMAP's own estimate comes out 35 % too long, which bends the trajectory and the geometry."""
    matching_overlap: int = 10
    """Sequential matching: each latent is matched with this many following latents."""
    quadratic_overlap: bool = True
    """Also match latents at quadratically growing distances (1, 2, 4, 8, ...) for long-range links."""
    max_num_features: int = 8192
    """Most SIFT features per latent."""
    num_threads: int = 1
    """CPU threads (-1: all). One thread makes the poses and points repeat exactly from run to run:
    with all threads, matching and mapping come out in a different order and the built-in scene's
    reconstruction differed between runs (562 against 536 points), which moved input-view PSNR by
    up to 0.8 dB. Two single-threaded runs wrote identical transforms.json and sparse_pc.ply; on the
    built-in scene it takes 16 s. Use -1 for large real captures."""
    init_min_num_inliers: int = 50
    """Inlier matches the mapper's initial image pair needs. COLMAP's default (100) is tuned for
    megapixel photos; the latents of small event-camera frames carry few features."""
    abs_pose_min_num_inliers: int = 15
    """2D-3D inliers needed to register a further latent (COLMAP's default 30 made tiny scenes split
    into several models)."""
    min_motion_px: float = 2.0
    """Before COLMAP runs, corners of the first latent are tracked into latents across the clip; when their
    median shift stays below this (px), the camera is static and COLMAP would register nothing: stop at once
    and say so (edygs_ns.preprocess.motion_check). 0: skip the check."""
    random_seed: int = 0
    """Seed of COLMAP's RANSAC and mapper (runs with more than one thread can still differ)."""
    extraction_batch: int = 16
    """Latents per feature-extraction call (granularity of the progress bar)."""
    feature_resolution: int = 512
    """COLMAP sees the latents upsampled by the smallest whole factor (at most 4) that brings their
    longer side to this many pixels: SIFT places features on tiny frames coarsely. 0: no upsampling."""
    mover_clusters: int = 5
    """Mover test: re-map without each k-means cluster (K = 2 .. this) of the map's points, so that a large
    moving object cannot carry the frame along (edygs_ns.preprocess.colmap_movers). 0 or 1: no test."""
    mover_error_ratio: float = 0.83
    """Mover test: a re-map replaces the map when its mean reprojection error is at most this times the map's ..."""
    mover_track_ratio: float = 1.15
    """... and its mean track length at least this times the map's (of such re-maps, the one with the most points)."""
    mover_margin_px: float = 2.0
    """Mover test: a cluster's image footprint (hull of its observations) is widened by this (latent pixels)."""


def with_calibration(config: ColmapConfig, intrinsics: Any) -> Tuple[ColmapConfig, str]:
    """`config` set up to use a known pinhole calibration, and a line saying what was done.

    Args:
        config: the user's COLMAP settings.
        intrinsics: an edygs_ns.geometry.Intrinsics at the latents' resolution, or None.

    Returns:
        (config unchanged when there is no calibration, when use_calibration is off or when
        camera_params is set by hand; else a copy with camera_params from the calibration and the
        focal length fixed. SIMPLE_PINHOLE becomes PINHOLE when fx and fy differ.)
    """
    if intrinsics is None:
        return config, "no calibration: COLMAP estimates the focal length"
    if not config.use_calibration:
        return config, "calibration known but not used (--colmap.no-use-calibration)"
    if config.camera_params is not None:
        return config, "calibration known; --colmap.camera-params given by hand is used instead"
    fx, fy, cx, cy = intrinsics.fl_x, intrinsics.fl_y, intrinsics.cx, intrinsics.cy
    model = config.camera_model
    if model == "SIMPLE_PINHOLE" and abs(fx - fy) > SQUARE_PIXEL_TOLERANCE * fx:
        model = "PINHOLE"
    values = {"SIMPLE_PINHOLE": [fx, cx, cy], "PINHOLE": [fx, fy, cx, cy], "OPENCV": [fx, fy, cx, cy, 0.0, 0.0, 0.0, 0.0]}[model]
    params = ",".join(f"{v:.10g}" for v in values)
    return replace(config, camera_model=model, camera_params=params, refine_focal_length=False), f"calibrated {model} {params}, fixed"


@dataclass(frozen=True)
class CameraEstimate(Intrinsics):
    """The shared camera COLMAP estimated: pinhole :class:`~edygs_ns.geometry.Intrinsics` plus the
    COLMAP model name and OpenCV distortion (zeros for PINHOLE)."""

    model: str = "PINHOLE"
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    @property
    def intrinsics(self) -> Intrinsics:
        """The pinhole part (distortion dropped)."""
        return Intrinsics(self.width, self.height, self.fl_x, self.fl_y, self.cx, self.cy)

    def distortion(self) -> np.ndarray:
        """[4] OpenCV distortion coefficients (k1, k2, p1, p2)."""
        return np.array([self.k1, self.k2, self.p1, self.p2])

    @property
    def distorted(self) -> bool:
        return bool(np.any(self.distortion() != 0.0))


@dataclass
class ColmapResult:
    """What COLMAP found for N latent images.

    Attributes:
        names: [N] image names in time order.
        c2w: [N, 4, 4] float64 camera-to-world (OpenGL axes), NaN for unregistered images.
        registered: [N] bool.
        camera: the shared camera, None when nothing registered.
        points_xyz: [P, 3] float64 sparse points (world frame of c2w).
        points_rgb: [P, 3] uint8 their colours.
        mean_reprojection_error: mean reprojection error in pixels (NaN without points).
        num_reconstructions: models COLMAP built (only the largest is kept).
        mover_test: the mover test's outcome (colmap_movers.MoverTest.as_dict, plus its "message");
            None when it did not run.
    """

    names: List[str]
    c2w: np.ndarray
    registered: np.ndarray
    camera: Optional[CameraEstimate]
    points_xyz: np.ndarray
    points_rgb: np.ndarray
    mean_reprojection_error: float
    num_reconstructions: int
    mover_test: Optional[Dict[str, Any]] = None

    @property
    def num_registered(self) -> int:
        return int(self.registered.sum())

    @property
    def unregistered_names(self) -> List[str]:
        return [n for n, ok in zip(self.names, self.registered) if not ok]

    def save(self, folder: Path) -> None:
        """Write the result to ``folder`` (result.npz + result.json)."""
        folder.mkdir(parents=True, exist_ok=True)
        np.savez(folder / RESULT_ARRAYS, c2w=self.c2w, registered=self.registered,
                 points_xyz=self.points_xyz, points_rgb=self.points_rgb)
        meta = {
            "names": self.names,
            "camera": asdict(self.camera) if self.camera is not None else None,
            "mean_reprojection_error": self.mean_reprojection_error,
            "num_reconstructions": self.num_reconstructions,
            "mover_test": self.mover_test,
        }
        (folder / RESULT_JSON).write_text(json.dumps(meta, indent=2))

    @classmethod
    def load(cls, folder: Path) -> "ColmapResult":
        """Read a result written by :meth:`save`."""
        meta = json.loads((folder / RESULT_JSON).read_text())
        with np.load(folder / RESULT_ARRAYS) as arrays:
            return cls(
                names=list(meta["names"]),
                c2w=arrays["c2w"],
                registered=arrays["registered"].astype(bool),
                camera=CameraEstimate(**meta["camera"]) if meta["camera"] is not None else None,
                points_xyz=arrays["points_xyz"],
                points_rgb=arrays["points_rgb"],
                mean_reprojection_error=float(meta["mean_reprojection_error"]),
                num_reconstructions=int(meta["num_reconstructions"]),
                mover_test=meta.get("mover_test"),
            )


def upsample_factor(width: int, height: int, feature_resolution: int) -> int:
    """Whole factor the latents are upsampled by for COLMAP: the smallest that brings the longer
    side to ``feature_resolution`` pixels, between 1 and MAX_UPSAMPLE (1 when it is 0)."""
    if feature_resolution <= 0:
        return 1
    return int(min(MAX_UPSAMPLE, max(1, -(-feature_resolution // max(width, height)))))


def scale_camera_params(model: str, params: str, factor: float) -> str:
    """COLMAP's parameter string ("f,cx,cy", ...) for images scaled by ``factor``: the pixel
    parameters scale (pixel centres at +0.5 map onto each other), distortion does not."""
    values = [float(v) for v in params.split(",")]
    n = PIXEL_PARAMS[model]
    return ",".join(f"{v * factor:.10g}" if i < n else f"{v:.10g}" for i, v in enumerate(values))


def _upsampled_images(image_dir: Path, names: Sequence[str], out_dir: Path, factor: int) -> Path:
    """Bicubic copies of the images, ``factor`` times larger, in ``out_dir`` (returned)."""
    from PIL import Image

    out_dir.mkdir(parents=True, exist_ok=True)
    with progress_bar(f"COLMAP: latents upsampled x{factor}", len(names)) as advance:
        for name in names:
            with Image.open(image_dir / name) as image:
                image.resize((image.width * factor, image.height * factor), Image.BICUBIC).save(out_dir / name)
            advance()
    return out_dir


def _camera_estimate(camera: "object", factor: int = 1) -> CameraEstimate:
    """The shared camera, with its pixel quantities divided by ``factor`` (the upsampling)."""
    params = np.asarray(camera.params, dtype=np.float64)
    extra = dict(zip(OPENCV_DISTORTION, params[list(camera.extra_params_idxs())].tolist()))
    return CameraEstimate(
        model=str(camera.model_name),
        width=int(camera.width) // factor,
        height=int(camera.height) // factor,
        fl_x=float(camera.focal_length_x) / factor,
        fl_y=float(camera.focal_length_y) / factor,
        cx=float(camera.principal_point_x) / factor,
        cy=float(camera.principal_point_y) / factor,
        **extra,
    )


def _extract(database: Path, image_dir: Path, names: Sequence[str], config: ColmapConfig) -> None:
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = config.camera_model
    if config.camera_params is not None:
        reader.camera_params = config.camera_params
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.use_gpu = False
    extraction.num_threads = config.num_threads
    extraction.sift.max_num_features = config.max_num_features
    batch = max(1, config.extraction_batch)
    with progress_bar("COLMAP: SIFT features", len(names)) as advance:
        for start in range(0, len(names), batch):
            if start > 0:
                reader.existing_camera_id = FIRST_CAMERA_ID  # later batches share the first camera
            pycolmap.extract_features(
                database, image_dir, image_names=list(names[start:start + batch]),
                camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                extraction_options=extraction, device=pycolmap.Device.cpu,
            )
            advance(len(names[start:start + batch]))


def _match(database: Path, config: ColmapConfig) -> None:
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    matching.num_threads = config.num_threads
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = config.matching_overlap
    pairing.quadratic_overlap = config.quadratic_overlap
    with progress_bar("COLMAP: sequential matching", None):
        pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)


def _mapper_options(config: ColmapConfig) -> "object":
    import pycolmap

    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = config.random_seed
    options.num_threads = config.num_threads
    options.extract_colors = True
    options.ba_refine_principal_point = False
    options.ba_refine_focal_length = config.refine_focal_length
    options.ba_refine_extra_params = config.refine_focal_length
    options.mapper.abs_pose_refine_focal_length = config.refine_focal_length
    options.mapper.abs_pose_refine_extra_params = config.refine_focal_length
    options.mapper.init_min_num_inliers = config.init_min_num_inliers
    options.mapper.abs_pose_min_num_inliers = config.abs_pose_min_num_inliers
    return options


def _map(database: Path, image_dir: Path, sparse_dir: Path, n_images: int, config: ColmapConfig) -> Dict[int, "object"]:
    import pycolmap

    options = _mapper_options(config)
    sparse_dir.mkdir(parents=True, exist_ok=True)
    with progress_bar("COLMAP: incremental mapping (images registered)", n_images) as advance:
        return pycolmap.incremental_mapping(
            database, image_dir, sparse_dir, options,
            initial_image_pair_callback=lambda: advance(INITIAL_PAIR), next_image_callback=advance,
        )


def run_colmap(image_dir: Path, names: Sequence[str], work_dir: Path, config: ColmapConfig) -> ColmapResult:
    """Reconstruct the latents with COLMAP and convert the largest model to the layout's frame.

    Args:
        image_dir: folder holding the images.
        names: N image names (file names in ``image_dir``) in time order.
        work_dir: scratch folder for the database and models (replaced).
        config: COLMAP settings.

    Returns:
        The result; images COLMAP did not register have NaN poses and registered=False.
    """
    import pycolmap

    pycolmap.logging.minloglevel = COLMAP_LOG_LEVEL
    if work_dir.exists():
        shutil.rmtree(work_dir)
    work_dir.mkdir(parents=True)
    database = work_dir / "database.db"
    factor = upsample_factor(*image_size(image_dir / names[0])[::-1], config.feature_resolution) if names else 1
    if factor > 1:
        image_dir = _upsampled_images(image_dir, names, work_dir / UPSAMPLED_DIR, factor)
        if config.camera_params is not None:
            config = replace(config, camera_params=scale_camera_params(config.camera_model, config.camera_params, factor))
    _extract(database, image_dir, names, config)
    _match(database, config)
    models = _map(database, image_dir, work_dir / "sparse", len(names), config)
    model = largest_model(models)
    mover_test = None
    if model is not None and config.mover_clusters >= 2:
        model, outcome = _mover_test(database, image_dir, work_dir, model, config, factor, names)
        mover_test = {**outcome.as_dict(), "message": outcome.message()}
    if factor > 1:
        shutil.rmtree(image_dir, ignore_errors=True)

    n = len(names)
    c2w = np.full((n, 4, 4), np.nan)
    registered = np.zeros(n, dtype=bool)
    empty = ColmapResult(list(names), c2w, registered, None, np.zeros((0, 3)), np.zeros((0, 3), np.uint8), float("nan"), len(models))
    if model is None:
        return empty
    index = {name: i for i, name in enumerate(names)}
    for image in model.images.values():
        if image.name in index and image.has_pose:
            i = index[image.name]
            c2w[i] = colmap_w2c_to_c2w_opengl(np.asarray(image.cam_from_world().matrix()))
            registered[i] = True
    camera = _camera_estimate(next(iter(model.cameras.values())), factor)
    points = list(model.points3D.values())
    xyz = np.array([p.xyz for p in points], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in points], dtype=np.uint8).reshape(-1, 3)
    return ColmapResult(
        names=list(names),
        c2w=c2w,
        registered=registered,
        camera=camera,
        points_xyz=xyz,
        points_rgb=rgb,
        mean_reprojection_error=float(model.compute_mean_reprojection_error()) / factor,
        num_reconstructions=len(models),
        mover_test=mover_test,
    )


def _mover_test(database: Path, image_dir: Path, work_dir: Path, model: "object", config: ColmapConfig,
                factor: int, names: Sequence[str]) -> Tuple["object", MoverTest]:
    """The mover test (colmap_movers) on the first map, mapping quietly with the same options."""
    import pycolmap

    options = _mapper_options(config)

    def remap(candidate_db: Path, sparse_dir: Path) -> Dict[int, "object"]:
        sparse_dir.mkdir(parents=True, exist_ok=True)
        return pycolmap.incremental_mapping(candidate_db, image_dir, sparse_dir, options)

    total = sum(range(2, config.mover_clusters + 1))
    with progress_bar("COLMAP: mover test (maps without a cluster of points)", total) as advance:
        model, outcome = remap_without_movers(database, model, work_dir / MOVER_TEST_DIR, remap, config.mover_clusters,
                                              config.mover_error_ratio, config.mover_track_ratio,
                                              config.mover_margin_px * factor, names, advance)
    # errors in latent pixels, like the result's
    return model, replace(outcome, error_before=outcome.error_before / factor, best_error=outcome.best_error / factor)


def registration_message(result: ColmapResult, min_fraction: float, shown: int) -> str:
    """The failure message when too few latents registered: how many, which, what to try."""
    total = len(result.names)
    missing = result.unregistered_names
    listed = ", ".join(missing[:shown]) + (f", ... ({len(missing) - shown} more)" if len(missing) > shown else "")
    return (
        f"COLMAP registered only {result.num_registered} of {total} latent frames "
        f"({result.num_registered / max(total, 1):.1%}, the minimum is {min_fraction:.0%}). "
        f"Not registered: {listed or 'none'}. No transforms.json was written. Try: a capture with more texture; "
        "a camera that moves (a static camera gives COLMAP no parallax); "
        "a smaller --frame-stride (more overlap between frames); a lower --k (fewer, cleaner latents); "
        "a larger --colmap.matching-overlap; --colmap.camera-model OPENCV if the lens distorts; "
        "--poses given with known poses (--given-poses FILE); or --min-registered-fraction to accept fewer "
        "(unregistered latents then get poses interpolated from their neighbours in time)."
    )

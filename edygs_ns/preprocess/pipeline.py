"""The preprocessing pipeline behind ``edygs-process``: from a raw capture to a trainable scene (the paper's "Pose Initialization").

Steps, each with a progress bar and a one-line summary with its time:

1. ``read``: read and validate the input (frame size vs event sensor, events covering every
   exposure), keep the selected frames (downscaled) in the work folder.
2. ``edi``: the event contrast threshold Θ estimated from the frames and events (one log line;
   ``--theta`` overrides it, see :mod:`edygs_ns.events.contrast`), then EDI latents for every
   exposure (k per frame) and the event maps between them.
3. ``poses``: COLMAP on the latents (SIFT, sequential matching, incremental mapping, one
   shared camera), or the poses given by the input (``--poses given``: a synthetic capture's
   gt/transforms.json, E2NeRF or EvDeblurNeRF poses, or ``--given-poses FILE``) with initial points
   triangulated from the latents at those poses (:mod:`edygs_ns.preprocess.triangulate`), or random
   points back-projected from random pixels of the latents (``--given-points random``, or with a
   warning when triangulation fails).
4. ``write``: the processed layout of docs/layouts.md, transforms.json last.

When COLMAP registers fewer than ``--min-registered-fraction`` of the latents the command stops
with a message (how many, which, what to try) and writes no transforms.json. Accepted
unregistered latents get poses interpolated in time from registered neighbours (listed in
process_report.json). Work products live in ``<output>/.edygs_work`` and finished steps are
recorded in ``<output>/.edygs_steps.json``: running again reuses them; ``--overwrite`` redoes all.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple

import numpy as np
import tyro
from nerfstudio.utils.rich_utils import CONSOLE
from typing_extensions import Annotated

from edygs_ns.events.accumulate import latent_times_us
from edygs_ns.events.color import decode_to_linear
from edygs_ns.events.contrast import ContrastAccumulator, ThetaChoice, choose_theta
from edygs_ns.events.edi import EdiConfig
from edygs_ns.events.exposures import Exposure, read_exposures
from edygs_ns.events.stream import bin_exposure
from edygs_ns.geometry import Intrinsics
from edygs_ns.io.images import UINT8_MAX, read_rgb_uint8, write_rgb_png
from edygs_ns.preprocess.cache import write_edi_latents
from edygs_ns.preprocess.colmap import ColmapConfig, ColmapResult, registration_message, run_colmap, with_calibration
from edygs_ns.preprocess.inputs import Capture, InputConfig, calibration_path, load_capture, read_image
from edygs_ns.preprocess.motion_check import check_camera_moves
from edygs_ns.preprocess.path_check import registered_path_notice
from edygs_ns.preprocess.steps import StepRunner, file_signature, fingerprint, progress_bar
from edygs_ns.preprocess.triangulate import GivenPoints, TriangulationConfig, initial_points_at_poses
from edygs_ns.preprocess.writer import (
    REPORT_NAME,
    SCENE_ENTRIES,
    SceneContent,
    blurry_name,
    complete_poses,
    latent_name,
    random_points_from_views,
    write_processed_scene,
)

#: Hidden work folder inside the output (intermediate products of the steps).
WORK_DIR_NAME = ".edygs_work"
#: Files in the work folder.
CAPTURE_JSON = "capture.json"
SHARP_GT_WORK = "sharp_gt"
GIVEN_POSES_NPZ = "given_poses.npz"
POSES_NPZ = "poses.npz"
EVENT_MAPS_WORK = "event_maps.npy"
CONTRAST_JSON = "contrast.json"
COLMAP_WORK = "colmap"
TRIANGULATION_WORK = "triangulation"
INITIAL_POINTS_JSON = "initial_points.json"
#: Microseconds per second (summaries in seconds).
US_PER_SECOND = 1_000_000
#: Unregistered latent names listed in the failure message (all are in process_report.json).
MESSAGE_MAX_NAMES = 10
#: Fallback depth range of random initial points, as multiples of the camera path's diameter,
#: when the input says nothing about depth.
FALLBACK_DEPTH_RANGE_PATH_MULTIPLES = (0.5, 5.0)
#: Fallback depth range (world units) when the cameras do not move either.
FALLBACK_DEPTH_RANGE = (0.5, 5.0)
#: Near depth of random points as a fraction of the far depth from scene.json's room bounds.
ROOM_NEAR_FRACTION = 0.05


class RegistrationError(RuntimeError):
    """COLMAP registered too few latents; the message says how many and what to try."""


@dataclass
class ProcessEdiConfig(EdiConfig):
    """EDI settings of edygs-process: as EdiConfig, but Θ is estimated from the capture by default."""

    theta: Optional[float] = None
    """Event contrast threshold (log-intensity change per event). None (default): estimated from the blurry
    frames and the events (edygs_ns.events.contrast; reported, and written to transforms.json). A value:
    used as given (the estimate is still reported)."""


@dataclass
class ProcessConfig:
    """Turn a raw capture (blurry frames + exposures + events) into a trainable EDyGS scene."""

    output: Path
    """Folder to write the processed scene into (created)."""
    inputs: Annotated[InputConfig, tyro.conf.arg(name="")] = field(default_factory=InputConfig)
    edi: Annotated[ProcessEdiConfig, tyro.conf.arg(name="")] = field(default_factory=ProcessEdiConfig)
    poses: Literal["colmap", "given"] = "colmap"
    """Where poses come from: COLMAP on the EDI latents, or the input's own poses (GT of a synthetic
    capture, E2NeRF or EvDeblurNeRF poses, or --given-poses FILE) with initial points from --given-points."""
    given_points: GivenPoints = "triangulated"
    """Initial points with --poses given: triangulated from the latents at the given poses (SIFT and matching as
    --colmap.*; random points, with a warning, when too few come out), or random (the behaviour before 2026-12)."""
    triangulation: TriangulationConfig = field(default_factory=TriangulationConfig)
    colmap: ColmapConfig = field(default_factory=ColmapConfig)
    min_registered_fraction: float = 0.9
    """Stop (and write no transforms.json) when COLMAP registers fewer than this share of the latents."""
    num_random_points: int = 20000
    """Random initial points (--given-points random, or the fallback): back-projected random pixels at random depths."""
    random_depth_range: Optional[Tuple[float, float]] = None
    """(near, far) depth of the random points, world units. None: from the input (E2NeRF/EvDeblurNeRF bounds,
    scene.json's room), else 0.5-5x the camera path's diameter."""
    seed: int = 0
    """Seed of the random initial points."""
    overwrite: bool = False
    """Redo every step and replace what this command wrote before (other files are left alone)."""


def work_dir(config: ProcessConfig) -> Path:
    return Path(config.output) / WORK_DIR_NAME


def _input_signature(config: InputConfig) -> List[Dict[str, Any]]:
    """File signatures of every input file, computed without reading the capture."""
    paths: List[Path] = []
    if config.aedat4 is not None:
        paths.append(Path(config.aedat4))
    if config.exposures is not None:
        csv_path = Path(config.exposures)
        paths.append(csv_path)
        paths += [e.file for e in read_exposures(csv_path)]
        gt = csv_path.resolve().parent / "gt" / "transforms.json"
        if gt.is_file():
            paths.append(gt)
    if config.events is not None:
        paths.append(Path(config.events))
    if config.e2nerf is not None:
        paths.append(Path(config.e2nerf))
    if config.evdeblurnerf is not None:
        paths += _evdeblurnerf_files(Path(config.evdeblurnerf))
    if config.given_poses is not None:
        paths.append(Path(config.given_poses))
    calibration = calibration_path(config)
    if calibration is not None:
        paths.append(calibration)
    return [file_signature(p) for p in paths]


def _evdeblurnerf_files(root: Path) -> List[Path]:
    """The files an EvDeblurNeRF scene's content depends on (not its edygs_cache/ of edygs-data)."""
    from edygs_ns.preprocess.evdeblurnerf import IMAGES_FOLDER

    files = [p for p in sorted(root.glob("*")) if p.is_file()] if root.is_dir() else [root]
    images = root / IMAGES_FOLDER
    return files + ([p for p in sorted(images.iterdir()) if p.is_file()] if images.is_dir() else [])


def _input_settings(config: InputConfig) -> Dict[str, Any]:
    """The input settings with paths resolved, so that spelling a path differently changes nothing."""
    return {k: str(Path(v).resolve()) if isinstance(v, Path) else v for k, v in asdict(config).items()}


def _input_roots(config: InputConfig) -> List[Path]:
    """Input files and folders the output folder must not contain."""
    roots = [config.aedat4, config.events, config.e2nerf, config.evdeblurnerf, config.given_poses, config.intrinsics]
    if config.exposures is not None:
        roots.append(Path(config.exposures).resolve().parent)
    return [Path(p) for p in roots if p is not None]


class Pipeline:
    """The four steps of edygs-process over one config; the capture is read only when needed."""

    def __init__(self, config: ProcessConfig) -> None:
        self.config = config
        self.work = work_dir(config)
        self.k = config.edi.k

    @cached_property
    def capture(self) -> Capture:
        return load_capture(self.config.inputs, self.k, want_given_poses=self.config.poses == "given")

    def close(self) -> None:
        if "capture" in self.__dict__:
            self.capture.close()

    # -- work-folder products ------------------------------------------------------------------

    def capture_meta(self) -> Dict[str, Any]:
        return json.loads((self.work / CAPTURE_JSON).read_text())

    def exposures(self) -> List[Exposure]:
        return [Exposure(int(f), int(s), int(e), Path(p)) for f, s, e, p in self.capture_meta()["exposures"]]

    def blurry_paths(self) -> List[Path]:
        return [self.work / "blurry" / blurry_name(i) for i in range(len(self.exposures()))]

    def latent_paths(self) -> List[List[Path]]:
        return [[self.work / "latents" / latent_name(i, j) for j in range(self.k)] for i in range(len(self.exposures()))]

    def theta_choice(self) -> ThetaChoice:
        """The Θ the edi step chose (and the estimate), kept in the work folder."""
        path = self.work / CONTRAST_JSON
        if not path.is_file():  # an edi step finished before Θ was estimated
            return choose_theta(None, self.config.edi.theta, "processed by an older edygs-process")
        return ThetaChoice.from_dict(json.loads(path.read_text()))

    def times_us(self) -> np.ndarray:
        return np.stack([latent_times_us(e.start_us, e.end_us, self.k) for e in self.exposures()])

    # -- steps ---------------------------------------------------------------------------------

    def read(self) -> str:
        """Read and validate the input; keep the selected frames and the capture's description."""
        capture = self.capture
        (self.work / "blurry").mkdir(parents=True, exist_ok=True)
        for i, frame in enumerate(capture.frames):
            write_rgb_png(self.work / "blurry" / blurry_name(i), frame)
        given = capture.given_poses if self.config.poses == "given" else None
        if given is not None:
            np.savez(self.work / GIVEN_POSES_NPZ, c2w=given.c2w)
        gt_dir = capture.gt_dir
        if capture.sharp_views is not None:
            gt_dir = self._write_sharp_ground_truth(capture)
        meta = {
            "form": capture.form,
            "source": capture.source,
            "height": capture.height,
            "width": capture.width,
            "exposures": [[e.frame, e.start_us, e.end_us, str(e.file)] for e in capture.exposures],
            "frame_names": capture.frame_names,
            "event_count_scale": capture.event_count_scale,
            "gt_dir": str(gt_dir) if gt_dir is not None else None,
            "scene_json": str(capture.scene_json) if capture.scene_json is not None else None,
            "given_intrinsics": asdict(given.intrinsics) if given is not None else None,
            "calibration": asdict(capture.calibration) if capture.calibration is not None else None,
            "calibration_source": capture.calibration_source,
            "given_source": given.source if given is not None else None,
            "given_depth_range": list(given.depth_range) if given is not None and given.depth_range else None,
            "dropped_frames": capture.dropped,
            "notes": capture.notes,
        }
        (self.work / CAPTURE_JSON).write_text(json.dumps(meta, indent=2))
        for note in capture.notes:
            CONSOLE.print(f"[yellow]note[/]: {note}", soft_wrap=True)
        if capture.events is not None:
            t0, t1 = capture.events.t_range()
            events = f"{len(capture.events):,} events over {(t1 - t0) / US_PER_SECOND:.2f} s"
        else:
            events = "pre-binned events"
        poses = f", given poses from {given.source}" if given is not None else ""
        if capture.sharp_views is not None:
            poses += f", {len(capture.sharp_views.image_paths)} sharp views kept as ground truth"
        return (f"{len(capture.frames)} frames {capture.width}x{capture.height} ({capture.form} input "
                f"{capture.source}), {events}{poses}")

    def _write_sharp_ground_truth(self, capture: Capture) -> Path:
        """The input's sharp views as a raw-capture style gt/ folder (novel views only) in the work folder."""
        views = capture.sharp_views
        assert views is not None
        folder = self.work / SHARP_GT_WORK
        if folder.exists():
            shutil.rmtree(folder)
        (folder / "novel").mkdir(parents=True)
        novel = []
        for i, (path, c2w, t_us) in enumerate(zip(views.image_paths, views.c2w, views.times_us)):
            name = f"novel/{i:04d}.png"
            write_rgb_png(folder / name, read_image(Path(path), self.config.inputs.alpha_background))
            novel.append({"file_path": name, "transform_matrix": np.asarray(c2w).tolist(), "time_us": int(t_us),
                          "source_file": str(path)})
        intr = views.intrinsics
        meta = {"w": intr.width, "h": intr.height, "fl_x": intr.fl_x, "fl_y": intr.fl_y, "cx": intr.cx, "cy": intr.cy,
                "camera_model": "PINHOLE", "frames": [], "novel_frames": novel}
        (folder / "transforms.json").write_text(json.dumps(meta, indent=2))
        return folder

    def edi(self) -> str:
        """EDI latents of every exposure, and the event maps [n, k-1, H, W] they used."""
        meta = self.capture_meta()
        exposures = self.exposures()
        n, h, w = len(exposures), meta["height"], meta["width"]
        (self.work / "latents").mkdir(parents=True, exist_ok=True)
        maps = np.lib.format.open_memmap(self.work / EVENT_MAPS_WORK, mode="w+", dtype=np.float32, shape=(n, self.k - 1, h, w))
        capture = self.capture
        blurry = self.blurry_paths()
        total_events = 0.0
        contrast = ContrastAccumulator(n)
        with progress_bar("Event bins", n) as advance:
            for i, exposure in enumerate(exposures):
                if capture.binned_events is not None:
                    bins = capture.binned_events[i]
                else:  # one chunked read per exposure, up to the next one: the EDI bins and the Θ fit share it
                    frame = decode_to_linear(read_rgb_uint8(blurry[i]) / UINT8_MAX, self.config.edi.color_space)
                    bins = bin_exposure(capture.events, exposures, i, self.k, meta["event_count_scale"], contrast, frame)
                maps[i] = bins
                total_events += float(np.abs(bins).sum())
                advance()
        reason = "the input's events are pre-binned per exposure" if capture.binned_events is not None else contrast.reason()
        choice = choose_theta(contrast.estimate(), self.config.edi.theta, reason, capture.default_theta,
                              capture.default_theta_origin)
        CONSOLE.print(choice.line())
        (self.work / CONTRAST_JSON).write_text(json.dumps(choice.to_dict(), indent=2))
        edi_config = replace(self.config.edi, theta=choice.theta)
        with progress_bar("EDI latents", n) as advance:
            write_edi_latents(blurry, maps, edi_config, self.latent_paths(), advance)
        maps.flush()
        del maps
        return (f"{n * self.k} latents from {n} frames (k={self.k}, theta={choice.theta:.3f} {choice.source}, "
                f"{self.config.edi.color_space}), total |signed bin count| {total_events:,.0f}")

    def poses(self) -> str:
        """COLMAP on the latents, or the given poses with triangulated (or random) initial points."""
        names = [p.name for row in self.latent_paths() for p in row]
        if self.config.poses == "colmap":
            check_camera_moves([row[len(row) // 2] for row in self.latent_paths()], self.config.colmap.min_motion_px)
            colmap, camera = self.colmap_settings()
            result = run_colmap(self.work / "latents", names, self.work / COLMAP_WORK, colmap)
            result.save(self.work / COLMAP_WORK)
            jumps = registered_path_notice(result.c2w, result.registered, result.names)
            if jumps:
                CONSOLE.print(jumps, soft_wrap=True, markup=False)
            error = f"{result.mean_reprojection_error:.3f} px" if np.isfinite(result.mean_reprojection_error) else "n/a"
            movers = f"; {result.mover_test['message']}" if result.mover_test else ""
            return (f"COLMAP registered {result.num_registered}/{len(names)} latents, {len(result.points_xyz):,} points, "
                    f"mean reprojection error {error}, {result.num_reconstructions} model(s); camera: {camera}{movers}")
        meta = self.capture_meta()
        with np.load(self.work / GIVEN_POSES_NPZ) as data:
            c2w = data["c2w"].reshape(-1, 4, 4)
        intrinsics = Intrinsics(**meta["given_intrinsics"])

        def random_points() -> Tuple[np.ndarray, np.ndarray, str]:
            depth_range = self._depth_range(meta, c2w)
            rng = np.random.default_rng(self.config.seed)
            flat_paths = [p for row in self.latent_paths() for p in row]
            xyz, rgb = random_points_from_views(flat_paths, c2w, intrinsics, depth_range, self.config.num_random_points, rng)
            return xyz, rgb, f"{len(xyz):,} random points at depths {depth_range[0]:.3g}-{depth_range[1]:.3g}"

        points = initial_points_at_poses(self.config.given_points, self.work / "latents", names, c2w, intrinsics,
                                         self.work / TRIANGULATION_WORK, self.config.colmap, self.config.triangulation,
                                         random_points)
        np.savez(self.work / POSES_NPZ, xyz=points.xyz, rgb=points.rgb)
        (self.work / INITIAL_POINTS_JSON).write_text(json.dumps(points.report(), indent=2))
        return f"given poses for {len(names)} latents from {meta['given_source']}; {points.summary}"

    def colmap_settings(self) -> Tuple[ColmapConfig, str]:
        """The COLMAP settings with the capture's calibration applied (with_calibration), and a note."""
        meta = self.capture_meta()
        calibration = meta.get("calibration")
        config, note = with_calibration(self.config.colmap, Intrinsics(**calibration) if calibration else None)
        if calibration:
            note += f" (from {meta.get('calibration_source')})"
        return config, note

    def _depth_range(self, meta: Dict[str, Any], c2w: np.ndarray) -> Tuple[float, float]:
        """Depth range of random points: config, input, scene.json's room, or the camera path."""
        if self.config.random_depth_range is not None:
            return tuple(self.config.random_depth_range)  # type: ignore[return-value]
        if meta["given_depth_range"] is not None:
            return tuple(meta["given_depth_range"])  # type: ignore[return-value]
        centres = c2w[:, :3, 3]
        if meta["scene_json"] is not None:
            scene = json.loads(Path(meta["scene_json"]).read_text())
            if "room_min" in scene and "room_max" in scene:
                corners = np.array(np.meshgrid(*zip(scene["room_min"], scene["room_max"]))).reshape(3, -1).T
                far = float(np.max(np.linalg.norm(corners[None] - centres[:, None], axis=-1)))
                return (ROOM_NEAR_FRACTION * far, far)
        diameter = float(np.max(np.linalg.norm(centres[None] - centres[:, None], axis=-1)))
        if diameter <= 0.0:
            return FALLBACK_DEPTH_RANGE
        return (FALLBACK_DEPTH_RANGE_PATH_MULTIPLES[0] * diameter, FALLBACK_DEPTH_RANGE_PATH_MULTIPLES[1] * diameter)

    def colmap_result(self) -> Optional[ColmapResult]:
        return ColmapResult.load(self.work / COLMAP_WORK) if self.config.poses == "colmap" else None

    def check_registration(self) -> None:
        """Raise RegistrationError (after writing a failure report) when too few latents registered."""
        result = self.colmap_result()
        if result is None:
            return
        total = len(result.names)
        if result.num_registered >= self.config.min_registered_fraction * total and result.num_registered > 0:
            return
        message = registration_message(result, self.config.min_registered_fraction, MESSAGE_MAX_NAMES)
        report = {"status": "failed", "error": message, **self.pose_report(result)}
        _write_report(Path(self.config.output) / REPORT_NAME, report)
        raise RegistrationError(message)

    def pose_report(self, result: Optional[ColmapResult]) -> Dict[str, Any]:
        n_latents = len(self.exposures()) * self.k
        if result is None:
            points = self.work / INITIAL_POINTS_JSON
            return {"pose_source": "given", "registered_latents": n_latents, "total_latents": n_latents,
                    "registered_fraction": 1.0, "unregistered_latents": [], "mean_reprojection_error_px": None,
                    "initial_points": json.loads(points.read_text()) if points.is_file() else None}
        error = result.mean_reprojection_error
        return {
            "pose_source": "colmap",
            "registered_latents": result.num_registered,
            "total_latents": len(result.names),
            "registered_fraction": result.num_registered / max(len(result.names), 1),
            "unregistered_latents": result.unregistered_names,
            "mean_reprojection_error_px": float(error) if np.isfinite(error) else None,
            "num_reconstructions": result.num_reconstructions,
            "mover_test": result.mover_test,
            "path_jumps": registered_path_notice(result.c2w, result.registered, result.names) or None,
            "camera": asdict(result.camera) if result.camera is not None else None,
            "camera_setting": self.colmap_settings()[1],
        }

    def write(self) -> str:
        """Write the processed layout (transforms.json last)."""
        scene = Path(self.config.output)
        for name in SCENE_ENTRIES:  # leftovers of an interrupted write step of ours
            path = scene / name
            if path.is_dir():
                shutil.rmtree(path)
            elif path.exists():
                path.unlink()
        meta = self.capture_meta()
        exposures = self.exposures()
        times = self.times_us()
        n, k = len(exposures), self.k
        result = self.colmap_result()
        if result is not None:
            c2w = complete_poses(result.c2w, result.registered, times.reshape(-1)).reshape(n, k, 4, 4)
            cam = result.camera
            intrinsics = cam.intrinsics
            distorted = cam if cam.distorted else None
            xyz, rgb = result.points_xyz, result.points_rgb
        else:
            with np.load(self.work / GIVEN_POSES_NPZ) as data:
                c2w = data["c2w"]
            with np.load(self.work / POSES_NPZ) as data:
                xyz, rgb = data["xyz"], data["rgb"]
            intrinsics = Intrinsics(**meta["given_intrinsics"])
            distorted = None
        gt_dir = Path(meta["gt_dir"]) if meta["gt_dir"] else None
        content = SceneContent(
            blurry=self.blurry_paths(), latents=self.latent_paths(), event_maps=self.work / EVENT_MAPS_WORK,
            exposures=exposures, times_us=times, c2w=c2w, intrinsics=intrinsics, distorted_camera=distorted,
            points_xyz=xyz, points_rgb=rgb, k=k, theta=self.theta_choice().theta,
            color_space=self.config.edi.color_space, pose_source=self.config.poses,
            gt_dir=gt_dir, gt_frame_map={e.frame: i for i, e in enumerate(exposures)},
        )
        written = write_processed_scene(scene, content, self.work)
        undistorted = " (undistorted from OPENCV)" if distorted is not None else ""
        return (f"{n * k} posed latents, {len(xyz):,} points, camera {written.width}x{written.height} "
                f"f=({written.fl_x:.1f}, {written.fl_y:.1f}){undistorted} -> {scene}")


def _write_report(path: Path, report: Dict[str, Any]) -> None:
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(json.dumps(report, indent=2))
    os.replace(tmp, path)


def process(config: ProcessConfig) -> Dict[str, Any]:
    """Run (or resume) every step of edygs-process; returns the process report.

    Raises:
        RegistrationError: COLMAP registered fewer latents than min_registered_fraction.
        FileExistsError: the output holds something else, or finished steps with other
            settings, and --overwrite was not given.
        FileNotFoundError / ValueError: bad inputs (the message names the file and the fault).
    """
    if not 0.0 <= config.min_registered_fraction <= 1.0:
        raise ValueError(f"min_registered_fraction must lie in [0, 1], got {config.min_registered_fraction}")
    if config.edi.theta is not None and not config.edi.theta > 0:
        raise ValueError(f"--theta must be positive, got {config.edi.theta}")
    output = Path(config.output)
    owned = SCENE_ENTRIES + (WORK_DIR_NAME,)
    runner = StepRunner(output, owned, config.overwrite, scratch=(WORK_DIR_NAME,))
    build = runner.prepare(_input_roots(config.inputs))  # a staging folder when --overwrite replaces a scene
    pipeline = Pipeline(dataclasses.replace(config, output=build))
    started = time.perf_counter()
    try:
        read_fp = fingerprint("read", _input_signature(config.inputs), _input_settings(config.inputs), config.poses,
                              config.edi.k if config.poses == "given" or config.inputs.e2nerf
                              or config.inputs.evdeblurnerf else None)
        runner.run("read", read_fp, pipeline.read)
        edi_fp = fingerprint("edi", read_fp, asdict(config.edi))
        runner.run("edi", edi_fp, pipeline.edi)
        pose_settings = asdict(config.colmap) if config.poses == "colmap" else [
            config.num_random_points, config.random_depth_range, config.seed, config.given_points,
            asdict(config.triangulation) if config.given_points == "triangulated" else None,
            asdict(config.colmap) if config.given_points == "triangulated" else None]
        poses_fp = fingerprint("poses", edi_fp, config.poses, pose_settings)
        runner.run("poses", poses_fp, pipeline.poses)
        pipeline.check_registration()
        runner.run("write", fingerprint("write", poses_fp), pipeline.write)
    except BaseException:
        pipeline.close()
        runner.abandon()
        raise
    pipeline.close()
    poses = pipeline.pose_report(pipeline.colmap_result())
    report = {
        "status": "ok",
        "input": pipeline.capture_meta()["source"],
        "input_form": pipeline.capture_meta()["form"],
        "n_blurry": len(pipeline.exposures()),
        "k": config.edi.k,
        "theta": pipeline.theta_choice().theta,
        "theta_source": pipeline.theta_choice().source,
        "theta_estimate": pipeline.theta_choice().to_dict()["estimate"],
        "color_space": config.edi.color_space,
        "downscale": config.inputs.downscale,
        "event_count_scale": pipeline.capture_meta()["event_count_scale"],
        "dropped_frames": pipeline.capture_meta().get("dropped_frames", []),
        "notes": pipeline.capture_meta().get("notes", []),
        **poses,
        "interpolated_latents": poses["unregistered_latents"],
        "num_points": _count_points(build),
        "step_seconds": {o.name: round(o.seconds, 3) for o in runner.outcomes},
        "steps_reused": [o.name for o in runner.outcomes if o.reused],
        "wall_seconds_this_run": round(time.perf_counter() - started, 3),
    }
    _write_report(build / REPORT_NAME, report)
    runner.commit()
    return report


def _count_points(scene: Path) -> int:
    from edygs_ns.io.ply import read_ply_points
    from edygs_ns.preprocess.writer import PLY_NAME

    return int(len(read_ply_points(scene / PLY_NAME)[0]))

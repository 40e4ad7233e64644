"""Write the built-in synthetic dynamic scene as a raw capture (docs/layouts.md); ``edygs-synth`` is its CLI.

A moving camera films a textured room with the moving objects of a scene preset (one textured
sphere by default; edygs_ns.sim.presets lists the suite). Each blurry frame is the mean of sharp
sub-frame renders over its exposure; the event stream comes from the event simulator fed with the
grey intensity of sharp renders at a fine time step over the whole clip. Ground truth (sharp
latents, dynamic-object masks and instance ids, true poses, novel views) goes under gt/.
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import shutil
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Iterable, Iterator, List, Optional, Sequence, Tuple

import numpy as np
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from edygs_ns.events.exposures import Exposure, write_exposures
from edygs_ns.events.types import EventArray
from edygs_ns.events.writers import write_events_h5
from edygs_ns.sim.presets import MovingObject, PresetContext, ScenePreset, build_objects
from edygs_ns.sim.covisibility import covisible_counts
from edygs_ns.sim.scene import PinholeCamera, Scene, build_scene, render, to_grey
from edygs_ns.sim.shapes import ObjectState, Shape
from edygs_ns.sim.simulator import EventSimulator, SimulatorConfig
from edygs_ns.sim.trajectory import US_PER_S, CameraPath, MotionKind, Timeline, make_camera_path, make_timeline
from edygs_ns.io.images import UINT8_MAX

#: What write_synthetic_scene writes into its folder (and removes first when overwriting).
OUTPUT_ENTRIES = ("exposures.csv", "frames", "events.h5", "gt", "scene.json", "camera.json")
#: Sub-seeds drawn from the config seed, one per random component.
SEED_STREAMS = ("scene", "camera", "object")
#: Ground-truth image folders under gt/: latent (training-path) views and novel views.
LATENT_DIRS = {"image": "sharp", "mask": "mask", "instance": "instance"}
NOVEL_DIRS = {"image": "novel", "mask": "novel_mask", "instance": "novel_instance"}
#: gt/ folder of the novel views' co-visibility: per pixel, how many training latents saw it (8-bit, capped).
NOVEL_COVISIBLE_DIR = "novel_covisible"


@dataclass
class SynthConfig:
    """Write the built-in synthetic dynamic scene (blurry frames, events, ground truth)."""

    output_dir: Path = Path("data/synthetic/raw")
    """Folder to write the raw capture into (created; must be empty unless --overwrite)."""
    width: int = 128
    """Image width in pixels."""
    height: int = 96
    """Image height in pixels."""
    fov_deg: float = 60.0
    """Horizontal field of view in degrees."""
    n_frames: int = 12
    """Number of blurry frames in the clip."""
    k: int = 5
    """Latent (sharp ground-truth) instants per exposure, first at its start, last at its end."""
    n_subframes: int = 9
    """Sharp renders averaged into one blurry frame, evenly spaced over the exposure (ends included)."""
    frame_interval_us: int = 100_000
    """Time between the starts of consecutive exposures, µs."""
    exposure_us: int = 80_000
    """Exposure time of each blurry frame, µs (at most frame_interval_us)."""
    sim_steps_per_exposure: int = 24
    """Event simulator steps per exposure time; the same step size is used between exposures."""
    contrast_threshold: float = 0.2
    """Event contrast threshold C (change of log intensity per event)."""
    threshold_sigma: float = 0.0
    """Standard deviation of the per-pixel contrast thresholds (0: all pixels use C)."""
    refractory_us: int = 0
    """Event refractory period per pixel, µs (0: none)."""
    seed: int = 0
    """Seed of textures, box placement, camera start, object paths and the simulator's thresholds."""
    preset: ScenePreset = "rigid"
    """Moving objects: rigid (one sphere, see --motion), two-objects, three-objects, articulated,
    deforming, enter-leave, large (covers ~1/3 of the image) or static (none)."""
    motion: MotionKind = "circular"
    """rigid preset: how the sphere moves: linear (back and forth), circular, or bouncing along the floor."""
    object_speed: float = 2.0
    """rigid preset: speed of the sphere, world units per second (the room is 4 units wide)."""
    object_radius: float = 0.35
    """rigid preset: radius of the sphere, world units."""
    camera_speed: float = 2.5
    """Speed of the camera centre along its elliptic sweep, world units per second."""
    camera_sway: float = 0.6
    """Lateral half-width of the camera sweep, world units (its height is 0.4 of this)."""
    camera_dolly: float = 0.4
    """Forward travel of the camera over the whole clip, world units."""
    novel_offset: float = 0.2
    """Novel views: camera centre moved outward from its sweep (sideways / up) by about this many
    world units, training orientation kept, so it is never on the training path."""
    novel_stride: int = 2
    """A novel view at the middle latent instant of every novel_stride-th blurry frame."""
    supersample: int = 2
    """Sub-pixel samples per pixel side for anti-aliasing (1: none)."""
    workers: int = 1
    """Processes rendering the simulator's instants and novel views in parallel (0: one per CPU
    core); the capture is the same."""
    overwrite: bool = False
    """Replace the capture in a non-empty output folder."""


def _validate(config: SynthConfig) -> None:
    """Raise ValueError naming the first field out of range (the timeline checks its own)."""
    positive = {
        "width": config.width, "height": config.height, "supersample": config.supersample,
        "novel_stride": config.novel_stride, "contrast_threshold": config.contrast_threshold,
        "object_radius": config.object_radius, "novel_offset": config.novel_offset,
    }
    for name, value in positive.items():
        if value <= 0:
            raise ValueError(f"SynthConfig.{name} must be positive, got {value}")
    non_negative = {
        "threshold_sigma": config.threshold_sigma, "refractory_us": config.refractory_us,
        "object_speed": config.object_speed, "camera_speed": config.camera_speed,
        "camera_sway": config.camera_sway, "workers": config.workers,
    }
    for name, value in non_negative.items():
        if value < 0:
            raise ValueError(f"SynthConfig.{name} must be >= 0, got {value}")


@dataclass(frozen=True)
class SynthWorld:
    """Everything needed to render the clip at any instant.

    Attributes:
        scene: the static geometry and its textures.
        camera: intrinsics.
        camera_path: camera pose over time.
        objects: the moving objects (instance id of objects[i] is i + 1).
        timeline: exposures, latents, sub-frames and simulator instants (µs).
        supersample: anti-aliasing factor of every render.
    """

    scene: Scene
    camera: PinholeCamera
    camera_path: CameraPath
    objects: Tuple[MovingObject, ...]
    timeline: Timeline
    supersample: int

    def c2w(self, t_us: int) -> np.ndarray:
        """[4, 4] true camera-to-world (OpenGL) at ``t_us``."""
        return self.camera_path.c2w(t_us / US_PER_S)

    def render(self, t_us: int, c2w: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray]:
        """Sharp view at ``t_us`` from the training camera (or from ``c2w`` if given).

        Returns:
            rgb: [H, W, 3] float32 linear intensity in [0, 1].
            instance: [H, W] uint8 instance ids (0 static, i + 1 for objects[i]); ``instance > 0``
                is the dynamic-object mask.
        """
        pose = self.c2w(t_us) if c2w is None else c2w
        return render(self.scene, self.camera, pose, self.posed(t_us), self.supersample)

    def posed(self, t_us: int) -> List[Tuple[Shape, ObjectState]]:
        """The moving shapes with their poses at ``t_us``."""
        return [(obj.shape, obj.state(t_us / US_PER_S)) for obj in self.objects]


def build_world(config: SynthConfig) -> SynthWorld:
    """Assemble the scene, camera, motions and timeline described by ``config`` (deterministic)."""
    _validate(config)
    timeline = make_timeline(config.n_frames, config.frame_interval_us, config.exposure_us, config.k,
                             config.n_subframes, config.sim_steps_per_exposure)
    seeds = np.random.SeedSequence(config.seed).spawn(len(SEED_STREAMS))
    rngs = dict(zip(SEED_STREAMS, (np.random.default_rng(s) for s in seeds)))
    scene_rng = np.random.default_rng(int(rngs["scene"].integers(2**31)))
    scene = build_scene(scene_rng)
    camera = PinholeCamera.from_fov(config.width, config.height, config.fov_deg)
    duration_s = timeline.duration_us / US_PER_S
    path = make_camera_path(rngs["camera"], config.camera_sway, config.camera_speed, config.camera_dolly, duration_s)
    context = PresetContext(path, camera, duration_s, config.motion, config.object_speed, config.object_radius,
                            scene.boxes)
    objects = build_objects(config.preset, scene_rng, rngs["object"], context)  # textures continue the room's stream
    return SynthWorld(scene, camera, path, objects, timeline, config.supersample)


def _prepare_output(folder: Path, overwrite: bool) -> None:
    """Create the folder tree; refuse a non-empty folder unless ``overwrite`` (then clear our entries)."""
    if folder.exists() and not folder.is_dir():
        raise FileExistsError(f"{folder}: output path exists and is not a folder")
    if folder.exists() and any(folder.iterdir()):
        if not overwrite:
            raise FileExistsError(f"{folder}: output folder is not empty; pass overwrite=True (--overwrite) to replace it")
        for name in OUTPUT_ENTRIES:
            entry = folder / name
            if entry.is_dir():
                shutil.rmtree(entry)
            elif entry.exists():
                entry.unlink()
    for sub in ["frames", f"gt/{NOVEL_COVISIBLE_DIR}"] + [f"gt/{d}" for dirs in (LATENT_DIRS, NOVEL_DIRS) for d in dirs.values()]:
        (folder / sub).mkdir(parents=True, exist_ok=True)


def _save_rgb(path: Path, rgb: np.ndarray) -> None:
    """Write linear [H, W, 3] values in [0, 1] as 8-bit RGB, no transfer curve."""
    Image.fromarray(np.rint(np.clip(rgb, 0.0, 1.0) * UINT8_MAX).astype(np.uint8)).save(path)


def _save_mask(path: Path, mask: np.ndarray) -> None:
    """Write a [H, W] bool mask as an 8-bit grey PNG (0 or 255)."""
    Image.fromarray(mask.astype(np.uint8) * UINT8_MAX).save(path)


def _save_gt(folder: Path, dirs: Dict[str, str], name: str, rgb: np.ndarray, instance: np.ndarray) -> None:
    """Write one ground-truth view: image, mask (instance > 0) and 8-bit instance ids."""
    _save_rgb(folder / "gt" / dirs["image"] / name, rgb)
    _save_mask(folder / "gt" / dirs["mask"] / name, instance > 0)
    Image.fromarray(instance).save(folder / "gt" / dirs["instance"] / name)


def _gt_entry(world: SynthWorld, dirs: Dict[str, str], name: str, pose: np.ndarray, t_us: int, p: int,
              j: int) -> Dict[str, Any]:
    """One ground-truth frame record of gt/transforms.json."""
    return {
        "file_path": f"{dirs['image']}/{name}",
        "mask_path": f"{dirs['mask']}/{name}",
        "instance_path": f"{dirs['instance']}/{name}",
        "transform_matrix": pose.tolist(),
        "time": float(world.timeline.normalised_time(t_us)),
        "time_us": int(t_us),
        "blurry_index": int(p),
        "latent_index": int(j),
    }


def _progress() -> Progress:
    """The progress bar over the clip's render instants (current blurry frame, event count)."""
    return Progress(
        TextColumn("[bold blue]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[events]:>9,} events"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=CONSOLE,
    )


#: The world the forked workers of _world_map draw (set before the pool starts).
_WORKER_WORLD: Optional[SynthWorld] = None


def _limit_worker_threads() -> None:
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return
    threadpool_limits(1)


def _in_worker(job: Tuple[Callable[[SynthWorld, Any], Any], Any]) -> Any:
    fn, item = job
    assert _WORKER_WORLD is not None
    return fn(_WORKER_WORLD, item)


@contextmanager
def _world_map(world: SynthWorld, fn: Callable[[SynthWorld, Any], Any], items: Sequence[Any], workers: int,
               chunksize: int = 1) -> Iterator[Iterable[Any]]:
    """``fn(world, item)`` for every item, in order: here, or by ``workers`` forked processes (0: one
    per core) where the platform forks. ``fn`` must be a module-level function."""
    global _WORKER_WORLD
    n = min(workers or os.cpu_count() or 1, len(items))
    if n <= 1 or "fork" not in multiprocessing.get_all_start_methods():
        yield (fn(world, item) for item in items)
        return
    _WORKER_WORLD = world
    try:
        with multiprocessing.get_context("fork").Pool(n, initializer=_limit_worker_threads) as pool:
            yield pool.imap(_in_worker, [(fn, item) for item in items], chunksize=chunksize)
    finally:
        _WORKER_WORLD = None


def _render_at(world: SynthWorld, t_us: int) -> Tuple[np.ndarray, np.ndarray]:
    return world.render(t_us)


def _novel_view(world: SynthWorld, item: Tuple[int, float]) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The novel view at (t µs, offset): its pose, render, instance ids and co-visibility counts."""
    t, offset = item
    pose = world.camera_path.novel_c2w(t / US_PER_S, offset)
    rgb, instance = world.render(t, pose)
    latent_times = [int(v) for v in world.timeline.latents.ravel()]
    counts = covisible_counts(world.scene, world.camera, pose, world.posed(t), [world.c2w(v) for v in latent_times],
                              [world.posed(v) for v in latent_times])
    return pose, rgb, instance, counts


def _simulate_clip(world: SynthWorld, config: SynthConfig, folder: Path) -> Tuple[EventArray, List[Dict[str, Any]]]:
    """Render every simulator instant once: feed the simulator, average sub-frames into blurry
    frames, save the latent ground truth. Returns the events and the latent records."""
    tl = world.timeline
    subframe_of: Dict[int, List[int]] = defaultdict(list)
    for p, row in enumerate(tl.subframes):
        for t in row:
            subframe_of[int(t)].append(p)
    latent_of: Dict[int, List[Tuple[int, int]]] = defaultdict(list)
    for p, row in enumerate(tl.latents):
        for j, t in enumerate(row):
            latent_of[int(t)].append((p, j))
    sums: Dict[int, np.ndarray] = {}
    counts: Dict[int, int] = defaultdict(int)
    sim = EventSimulator(config.height, config.width, SimulatorConfig(
        contrast_threshold=config.contrast_threshold, threshold_sigma=config.threshold_sigma,
        refractory_us=config.refractory_us, seed=config.seed))
    parts: List[EventArray] = []
    n_events = 0
    records: List[Dict[str, Any]] = []
    with _progress() as progress:
        task = progress.add_task("frame 0", total=len(tl.sim_times), events=0)
        times = [int(v) for v in tl.sim_times]
        with _world_map(world, _render_at, times, config.workers, chunksize=4) as renders:
            for t, (rgb, instance) in zip(times, renders):
                events = sim.feed(to_grey(rgb), t)
                parts.append(events)
                n_events += len(events)
                for p in subframe_of.get(t, ()):
                    sums[p] = sums.get(p, 0.0) + rgb.astype(np.float64)
                    counts[p] += 1
                    if counts[p] == config.n_subframes:
                        _save_rgb(folder / "frames" / f"{p:04d}.png", sums.pop(p) / config.n_subframes)
                for p, j in latent_of.get(t, ()):
                    name = f"{p:04d}_{j}.png"
                    _save_gt(folder, LATENT_DIRS, name, rgb, instance)
                    records.append(_gt_entry(world, LATENT_DIRS, name, world.c2w(t), t, p, j))
                frame = int(np.searchsorted(tl.exposure_start, t, side="right")) - 1
                progress.update(task, advance=1, events=n_events, description=f"frame {max(frame, 0) + 1}/{config.n_frames}")
    events = EventArray(
        x=np.concatenate([e.x for e in parts]),
        y=np.concatenate([e.y for e in parts]),
        t=np.concatenate([e.t for e in parts]),
        p=np.concatenate([e.p for e in parts]),
        sensor_size=(config.height, config.width),
    )
    return events, records


def _render_novel(world: SynthWorld, config: SynthConfig, folder: Path) -> List[Dict[str, Any]]:
    """Sharp views off the training path at the middle latent of every novel_stride-th frame, and
    how many training latents saw each of their pixels (sim/covisibility.py)."""
    j = (config.k - 1) // 2
    records = []
    frames = list(range(0, config.n_frames, config.novel_stride))
    items = [(int(world.timeline.latents[p, j]), config.novel_offset) for p in frames]
    with _world_map(world, _novel_view, items, config.workers) as views:
        for p, (t, _), (pose, rgb, instance, counts) in zip(frames, items, views):
            name = f"{p:04d}_{j}.png"
            _save_gt(folder, NOVEL_DIRS, name, rgb, instance)
            Image.fromarray(np.minimum(counts, UINT8_MAX).astype(np.uint8)).save(folder / "gt" / NOVEL_COVISIBLE_DIR / name)
            records.append({**_gt_entry(world, NOVEL_DIRS, name, pose, t, p, j), "covisible_path": f"{NOVEL_COVISIBLE_DIR}/{name}"})
    return records


def _camera_path_diameter(world: SynthWorld) -> float:
    """Largest distance between two true camera centres at the latent instants, world units."""
    centres = np.stack([world.c2w(int(t))[:3, 3] for t in world.timeline.latents.ravel()])
    return float(np.max(np.linalg.norm(centres[:, None, :] - centres[None, :, :], axis=-1)))


def _config_json(config: SynthConfig) -> Dict[str, Any]:
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(config).items()}


def write_synthetic_scene(config: SynthConfig) -> Path:
    """Write the synthetic scene as a raw capture in ``config.output_dir``.

    Writes exposures.csv, frames/NNNN.png (8-bit, linear values quantised directly), events.h5,
    camera.json (the camera's calibration, as a real capture's would be: w, h, fl_x, fl_y, cx, cy),
    gt/ (transforms.json with the latent and novel frames; sharp/, mask/ (union of all moving
    objects), instance/ (8-bit ids: 0 static, i + 1 for moving object i) and the same for the
    novel views: novel/, novel_mask/, novel_instance/) and scene.json (the config, the preset and
    its objects, the event count and the scene extent for ATE normalisation).

    Args:
        config: what to write.

    Returns:
        The output folder.

    Raises:
        ValueError: a config field is out of range.
        FileExistsError: the output folder is not empty and ``config.overwrite`` is False.
    """
    world = build_world(config)
    folder = Path(config.output_dir)
    _prepare_output(folder, config.overwrite)
    events, latent_records = _simulate_clip(world, config, folder)
    novel_records = _render_novel(world, config, folder)
    write_events_h5(folder / "events.h5", events, overwrite=True)
    tl = world.timeline
    exposures = [Exposure(p, int(tl.exposure_start[p]), int(tl.exposure_end[p]), folder / "frames" / f"{p:04d}.png")
                 for p in range(config.n_frames)]
    write_exposures(folder / "exposures.csv", exposures, relative_to=folder)
    cam = world.camera
    calibration = {"w": cam.width, "h": cam.height, "fl_x": cam.fl_x, "fl_y": cam.fl_y, "cx": cam.cx, "cy": cam.cy}
    (folder / "camera.json").write_text(json.dumps(calibration, indent=2))
    transforms = {
        **calibration, "camera_model": "PINHOLE", "k": config.k, "theta": config.contrast_threshold, "color_space": "linear",
        "frames": latent_records, "novel_frames": novel_records,
    }
    (folder / "gt" / "transforms.json").write_text(json.dumps(transforms, indent=2))
    summary = {
        "config": _config_json(config),
        "preset": config.preset,
        "objects": [{"id": i + 1, **obj.describe()} for i, obj in enumerate(world.objects)],
        "n_blurry_frames": config.n_frames,
        "n_events": len(events),
        "duration_us": tl.duration_us,
        "camera_path_diameter": _camera_path_diameter(world),
        "room_diameter": world.scene.room_diameter,
        "room_min": world.scene.room_min.tolist(),
        "room_max": world.scene.room_max.tolist(),
    }
    (folder / "scene.json").write_text(json.dumps(summary, indent=2))
    return folder

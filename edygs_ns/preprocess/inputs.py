"""Every input form of ``edygs-process``, turned into one neutral :class:`Capture`.

Input forms:

- (a) ``--aedat4 FILE``: a DAVIS recording; APS frames with their exposure begin/end and the
  event stream, in one file. It carries no poses.
- (b) ``--exposures CSV --events FILE``: an exposure table (docs/layouts.md) naming the blurry
  frames, and events in any format :mod:`edygs_ns.events.readers` reads. When the CSV sits in a
  raw capture written by ``edygs-synth``, its ``gt/transforms.json`` gives the poses for
  ``--poses given`` and ``gt/`` is copied into the processed scene.
- (c) a published benchmark scene to re-pose (or keep its poses with ``--poses given``):

  - ``--e2nerf DIR``: an E2NeRF scene, synthetic (Blender style: ``transform_train.json``,
    ``train/r_*.png``, ``events.pt``) or real (LLFF style: ``poses_bounds.npy``, ``images/``,
    ``events.pt`` or ``event.pt``). Its events are already binned (4 bins per frame), so k - 1
    must divide 4, and the format stores no timestamps: exposures are placed on a nominal clock
    (:data:`E2NERF_FRAME_PERIOD_US`; exposures of :data:`E2NERF_REAL_EXPOSURE_US`, E2NeRF's four
    fixed 25.001 ms bins, and :data:`E2NERF_SYNTHETIC_EXPOSURE_US`, sub-frames 0..17), which only
    sets the normalised latent times. As E2NeRF reads them: synthetic frames keep their stored
    RGB (alpha dropped, its ``white_bkgd = False``) and their latents are sub-frames 0, 5, 9,
    13, 17; real data's EDI uses Θ = 0.3 (:attr:`Capture.default_theta`; the pre-binned events
    give no Θ estimate). :mod:`.e2nerf` reads the folder (the dataparser's layouts use it too); a
    ``gt/`` folder in the raw-capture format beside it (:mod:`.e2nerf_writer`) is copied as ground truth.
  - ``--evdeblurnerf DIR``: an EvDeblurNeRF scene (``images_1/`` with ``timestamps.npz``,
    ``poses_bounds.npy``, ``events.h5``; :mod:`edygs_ns.preprocess.evdeblurnerf` describes
    the format and its sources). Raw events with real exposure times, so any k works. The
    blurry frames are the images whose exposure has a length; the sharp held-out views become
    the processed scene's ground-truth novel views. Given poses are the scene's camera path
    interpolated at each latent instant.

A capture holds the selected frames (frame range/stride applied), downscaled by an integer
factor together with the event coordinates. Pixel values are stored 8-bit RGB as read: grey
frames are repeated over three channels, alpha is composited over a white or black background
or dropped (``--alpha-background``; by default as the input's authors do: dropped for E2NeRF,
white otherwise), 16-bit images are scaled to 8 bits with one bit depth per capture
(:mod:`.frames`).

Frames whose exposure the events do not cover are dropped with a notice when they are few, or
refused with the options that fix it (:mod:`edygs_ns.events.coverage`); the event time unit
is given (``--events-time-unit``) or detected from the spans, and the decision is logged. Every
notice is one line in ``Capture.notes``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, List, Literal, Optional, Sequence, Tuple

import cv2
import numpy as np

from edygs_ns.events.accumulate import latent_times_us
from edygs_ns.events.coverage import measure_coverage, resolve_coverage
from edygs_ns.events.exposures import Exposure, check_exposure_sequence, read_exposures
from edygs_ns.events.readers import (
    READ_CHUNK_EVENTS, ArrayEventSource, EventSource, native_time_unit, open_event_source, read_aedat4,
)
from edygs_ns.events.types import EventArray
from edygs_ns.events.units import AUTO_UNIT, US_PER_TICK, detect_time_unit
from edygs_ns.preprocess.frames import frames_to_rgb8, read_frames, read_raw_image, to_rgb8  # noqa: F401 (re-exported)
from edygs_ns.geometry import Intrinsics, interpolate_poses
from edygs_ns.preprocess import e2nerf

#: Name of the ground-truth folder of a raw capture, and its pose file.
GT_DIR_NAME = "gt"
GT_TRANSFORMS_NAME = "transforms.json"
#: Scene description written by edygs-synth next to exposures.csv (carries the scene extent).
SCENE_JSON_NAME = "scene.json"
#: Camera calibration file looked for next to an exposure table when --intrinsics is not given.
CALIBRATION_NAME = "camera.json"
#: Largest relative difference of width/height aspect between a calibration and the frames.
CALIBRATION_ASPECT_TOLERANCE = 1e-2
#: E2NeRF stores this many event bins per blurry frame (5 latents); :mod:`.e2nerf` reads its scenes.
E2NERF_BINS = e2nerf.BINS
#: Nominal clock of E2NeRF frames, which store no timestamps: frame i is exposed over
#: [i * period, i * period + exposure) µs. Only normalised latent times depend on it.
E2NERF_FRAME_PERIOD_US = 200_000
#: Real data: E2NeRF bins events in fixed 25.001 ms windows from the exposure start, 4 of them:
#: the latents (bin edges) sit at start + j * 25.001 ms.
E2NERF_REAL_BIN_US = e2nerf.BIN_US
E2NERF_REAL_EXPOSURE_US = E2NERF_BINS * E2NERF_REAL_BIN_US
#: Synthetic data: sub-frames 10 ms apart, the blur spans sub-frames 0..17. Its latents (0, 5,
#: 9, 13, 17) are not evenly spaced; the processed scene spaces them evenly (times only).
E2NERF_SYNTHETIC_EXPOSURE_US = e2nerf.LAST_SUBFRAME * e2nerf.SUBFRAME_US
#: Default Θ of E2NeRF real data (its EDI.py), used when no --theta is given.
E2NERF_REAL_THETA = e2nerf.REAL_THETA
#: E2NeRF reads RGBA frames without compositing (white_bkgd = False): alpha is dropped.
E2NERF_ALPHA_BACKGROUND = "none"
#: What a coverage error suggests checking (edygs-process can convert and shift the event clock).
COVERAGE_HINT = ("check the event clock: --events-time-unit (the unit of the file's timestamps) and "
                 "--events-t-offset-us (µs added to them)")
#: What a coverage error of an AEDAT4 recording suggests (frames and events share one clock).
AEDAT4_COVERAGE_HINT = "the recording's frames and events do not overlap (check --events-time-unit)"
#: Fragment of the readers' error when a file stores no sensor size (then the frame size is used).
NO_SENSOR_SIZE_MESSAGE = "does not store the sensor size"


@dataclass
class InputConfig:
    """Where the capture comes from, which frames to take, and at which resolution."""

    aedat4: Optional[Path] = None
    """Input form (a): a DAVIS AEDAT4 recording (APS frames with exposures + events)."""
    exposures: Optional[Path] = None
    """Input form (b): the exposure table (frame,exposure_start_us,exposure_end_us,file); needs --events."""
    events: Optional[Path] = None
    """Input form (b): the event file (.h5, .npz, .npy, .txt, .aedat4)."""
    e2nerf: Optional[Path] = None
    """Input form (c): an E2NeRF synthetic (transform_train.json) or real (poses_bounds.npy) scene folder."""
    evdeblurnerf: Optional[Path] = None
    """Input form (c): an EvDeblurNeRF scene folder (images_1/ + timestamps.npz, poses_bounds.npy, events.h5)."""
    evdeblurnerf_events_unit: Literal["auto", "us", "ns"] = "auto"
    """Unit of t in an EvDeblurNeRF events.h5 (the file does not say: the authors' Blender scenes use ns,
    their CDAVIS scenes us). "auto": the unit under which the events last about as long as the images."""
    evdeblurnerf_timestamps_unit: Literal["us", "ns"] = "us"
    """Unit of an EvDeblurNeRF scene's timestamps.npz and all_timestamps.npy (the authors' configs: us)."""
    intrinsics: Optional[Path] = None
    """The camera's calibration: a JSON file with w, h and fl_x [, fl_y, cx, cy] (or camera_angle_x) in
    pixels of the full-size frames (a nerfstudio transforms.json works). COLMAP then uses it (see
    --colmap.use-calibration). Default: camera.json next to the exposure table if there is one; the
    E2NeRF and EvDeblurNeRF scenes carry their own."""
    given_poses: Optional[Path] = None
    """With --poses given: a transforms.json with one frame per latent (blurry_index, latent_index or
    time_us, transform_matrix). Default: gt/transforms.json next to the exposure table, or the E2NeRF /
    EvDeblurNeRF poses."""
    events_t_offset_us: Optional[int] = None
    """Microseconds added to every event timestamp (replaces the file's own t_offset)."""
    events_time_unit: Literal["auto", "s", "ms", "us", "ns"] = "auto"
    """Unit of the event timestamps, for every input with events. "auto": the unit under which the events
    last about as long as the exposures (logged); AEDAT4 recordings are µs by the format. Overrides
    --evdeblurnerf-events-unit; E2NeRF events are pre-binned and carry no timestamps."""
    frame_bits: Optional[int] = None
    """Significant bits of 16-bit frames (10, 12, 14 or 16). None: the smallest depth holding the largest
    code of all the frames (logged), so 12-bit data in 16-bit PNGs is not darkened 16 times."""
    frame_start: int = 0
    """First blurry frame to use (index into the input's frame list)."""
    frame_end: Optional[int] = None
    """One past the last blurry frame to use (None: up to the last frame)."""
    frame_stride: int = 1
    """Use every frame_stride-th frame from frame_start."""
    downscale: int = 1
    """Integer factor dividing the frame size and the event coordinates (counts are area-averaged)."""
    alpha_background: Literal["auto", "white", "black", "none"] = "auto"
    """Background that RGBA frames are composited over; "none" drops alpha and keeps the stored RGB.
    "auto": as the input's authors read it: "none" for E2NeRF (its white_bkgd = False), else "white"."""
    evdeblurnerf_coordinates: Literal["bilinear", "round"] = "bilinear"
    """How an EvDeblurNeRF scene's rectified (floating-point) event coordinates become pixels: splatted
    bilinearly over the four neighbours (the authors' EDI prior) or rounded to the nearest pixel."""


@dataclass
class GivenPoses:
    """Poses taken from the input instead of COLMAP.

    Attributes:
        c2w: [n, k, 4, 4] float64 camera-to-world (OpenGL axes), latent j of selected frame i.
        intrinsics: the camera at the capture's (downscaled) resolution.
        source: the file the poses came from.
        depth_range: (near, far) world-unit depths where the scene lies, when the input says.
    """

    c2w: np.ndarray
    intrinsics: Intrinsics
    source: str
    depth_range: Optional[Tuple[float, float]] = None


@dataclass
class SharpViews:
    """Sharp images with known poses and instants, kept as the processed scene's novel views.

    Attributes:
        image_paths: V sharp images (same size as the capture's frames before downscaling).
        c2w: [V, 4, 4] OpenGL camera-to-world, in the world frame of the given poses.
        times_us: [V] int64 instant of each view on the event clock.
        intrinsics: the camera of these images, at their stored size.
    """

    image_paths: List[Path]
    c2w: np.ndarray
    times_us: np.ndarray
    intrinsics: Intrinsics


@dataclass
class Capture:
    """The neutral form of every input: blurry frames, exposures, events, optional poses.

    Attributes:
        form: which input form it came from ("aedat4", "exposures", "e2nerf" or "evdeblurnerf").
        source: the input file or folder, for messages and the report.
        frames: n uint8 [H, W, 3] blurry frames (selected and downscaled).
        frame_names: n names of the frames' origin, for messages.
        exposures: n exposures (µs on the event clock); ``file`` is the frame's origin.
        events: windowed event source at the capture's resolution, or None when binned.
        binned_events: [n, k-1, H, W] float32 signed counts when the input stores bins, else None.
        event_count_scale: factor applied to accumulated counts (1 / downscale², the area
            average that keeps count * theta a log-intensity change).
        given_poses: poses from the input, when asked for and available.
        calibration: the camera's intrinsics at the capture's (downscaled) resolution, when known.
        calibration_source: where `calibration` came from.
        gt_dir: ground-truth folder to copy into the processed scene, if any.
        scene_json: the raw capture's scene.json, if any.
        sharp_views: sharp views to write as ground-truth novel views, if the input has them.
        default_theta: the contrast threshold the input's authors use, for when Θ is neither
            given (--theta) nor estimated from the data (None: the global fallback).
        default_theta_origin: where default_theta comes from, for the log line.
        input_paths: files whose content the processing depends on (fingerprints).
        selected: n indices of the selected frames in the input's frame list.
        dropped: indices (input's frame list) of selected frames dropped as not covered by events.
        notes: one-line notices of what was assumed or dropped while reading.
    """

    form: str
    source: str
    frames: List[np.ndarray]
    frame_names: List[str]
    exposures: List[Exposure]
    events: Optional[EventSource]
    binned_events: Optional[np.ndarray]
    event_count_scale: float
    given_poses: Optional[GivenPoses] = None
    calibration: Optional[Intrinsics] = None
    calibration_source: Optional[str] = None
    gt_dir: Optional[Path] = None
    scene_json: Optional[Path] = None
    sharp_views: Optional[SharpViews] = None
    default_theta: Optional[float] = None
    default_theta_origin: str = ""
    input_paths: List[Path] = field(default_factory=list)
    selected: List[int] = field(default_factory=list)
    dropped: List[int] = field(default_factory=list)
    notes: List[str] = field(default_factory=list)

    @property
    def height(self) -> int:
        return int(self.frames[0].shape[0])

    @property
    def width(self) -> int:
        return int(self.frames[0].shape[1])

    def close(self) -> None:
        """Release the event file."""
        if self.events is not None:
            self.events.close()


class DownscaledEventSource(EventSource):
    """Events of another source with coordinates divided by an integer factor.

    Events falling outside the downscaled sensor (the cropped remainder when the size is not a
    multiple of the factor) are dropped.
    """

    def __init__(self, base: EventSource, factor: int) -> None:
        h, w = base.sensor_size
        super().__init__(f"{base.name} (downscaled x{factor})", (h // factor, w // factor))
        self.base = base
        self.factor = int(factor)

    def _scale(self, events: EventArray) -> EventArray:
        x = events.x // self.factor
        y = events.y // self.factor
        keep = (x < self.sensor_size[1]) & (y < self.sensor_size[0])
        weight = events.weight[keep] if events.weight is not None else None
        return EventArray(x[keep], y[keep], events.t[keep], events.p[keep], self.sensor_size, weight)

    def __len__(self) -> int:
        return len(self.base)

    def t_range(self) -> Tuple[int, int]:
        return self.base.t_range()

    def window(self, t_start_us: int, t_end_us: int) -> EventArray:
        return self._scale(self.base.window(t_start_us, t_end_us))

    def chunks(self, t_start_us: int, t_end_us: int, max_events: int = READ_CHUNK_EVENTS) -> Iterator[EventArray]:
        return (self._scale(chunk) for chunk in self.base.chunks(t_start_us, t_end_us, max_events))

    def read_all(self) -> EventArray:
        return self._scale(self.base.read_all())

    def close(self) -> None:
        self.base.close()


# ----------------------------------------------------------------------------------------------
# Frames


def resolve_alpha_background(config: InputConfig, own: str = "white") -> str:
    """--alpha-background, or the input's own convention ``own`` when it is "auto"."""
    return own if config.alpha_background == "auto" else config.alpha_background



def read_image(path: Path, alpha_background: Optional[str] = "white", bits: Optional[int] = None) -> np.ndarray:
    """Read one image file as uint8 [H, W, 3] RGB (its bit depth judged alone; see :mod:`.frames`)."""
    return read_frames([Path(path)], alpha_background, bits)[0][0]


def downscale_image(image: np.ndarray, factor: int) -> np.ndarray:
    """Area-average an image by an integer factor ([H, W, C] -> [H // f, W // f, C])."""
    if factor == 1:
        return image
    h, w = image.shape[:2]
    return cv2.resize(image, (w // factor, h // factor), interpolation=cv2.INTER_AREA)


def downscale_counts(maps: np.ndarray, factor: int) -> np.ndarray:
    """Area-average event-count maps [..., H, W] by an integer factor (remainder cropped)."""
    if factor == 1:
        return maps
    h, w = maps.shape[-2] // factor, maps.shape[-1] // factor
    cropped = maps[..., : h * factor, : w * factor]
    blocks = cropped.reshape(maps.shape[:-2] + (h, factor, w, factor))
    return blocks.mean(axis=(-3, -1)).astype(np.float32)


def select_indices(n: int, config: InputConfig, source: str) -> List[int]:
    """Indices of the frames kept by frame_start / frame_end / frame_stride.

    Raises:
        ValueError: a bad range or stride, or nothing selected (names the source).
    """
    if config.frame_stride < 1:
        raise ValueError(f"frame_stride must be at least 1, got {config.frame_stride}")
    if config.downscale < 1:
        raise ValueError(f"downscale must be at least 1, got {config.downscale}")
    end = n if config.frame_end is None else min(config.frame_end, n)
    indices = list(range(max(config.frame_start, 0), end, config.frame_stride))
    if not indices:
        raise ValueError(
            f"{source}: no frame selected by frame_start={config.frame_start}, frame_end={config.frame_end}, "
            f"frame_stride={config.frame_stride} (the input has {n} frames)"
        )
    return indices


# ----------------------------------------------------------------------------------------------
# Events


def _open_in_unit(path: Path, frame_size: Tuple[int, int], t_offset_us: Optional[int], unit: str) -> EventSource:
    """Open an event file in a time unit; when it stores no sensor size the frames' size is used."""
    try:
        return open_event_source(path, None, t_offset_us, unit)
    except ValueError as err:
        if NO_SENSOR_SIZE_MESSAGE not in str(err):
            raise
        return open_event_source(path, frame_size, t_offset_us, unit)


def exposure_span_us(exposures: Sequence[Exposure]) -> int:
    """µs from the first exposure's start to the last one's end."""
    return int(max(e.end_us for e in exposures) - min(e.start_us for e in exposures))


def _open_events(
    path: Path, frame_size: Tuple[int, int], t_offset_us: Optional[int], unit: str, exposures: Sequence[Exposure],
    notes: List[str],
) -> EventSource:
    """Open an event file in the given unit, or detect the unit from the spans ("auto") and say so in ``notes``.

    A given unit under which the spans disagree (another unit fits them better) is kept, with a note.
    """
    default = native_time_unit(path) if unit == AUTO_UNIT else unit
    source = _open_in_unit(path, frame_size, t_offset_us, default)
    try:
        t_first, t_last = source.t_range()
    except ValueError:
        return source  # no events: the coverage check says so
    detected, reason = detect_time_unit((t_last - t_first) / US_PER_TICK[default], exposure_span_us(exposures), default)
    if unit != AUTO_UNIT:
        if detected != unit:
            notes.append(f"{path}: event timestamps read in {unit} as given, but {reason} (is --events-time-unit right?)")
        return source
    notes.append(f"{path}: event timestamps read in {detected} (auto-detected: {reason}; --events-time-unit overrides)")
    if detected == default:
        return source
    source.close()
    return _open_in_unit(path, frame_size, t_offset_us, detected)


def cover_frames(
    events: EventSource, exposures: Sequence[Exposure], names: Sequence[str], selected: Sequence[int], k: int, hint: str
) -> Tuple[List[int], List[str]]:
    """Positions of the frames the events cover and the notices (see :mod:`edygs_ns.events.coverage`).

    Raises:
        ValueError: no events, or too many frames not covered (names the options that fix it).
    """
    try:
        t_first, t_last = events.t_range()
    except ValueError as err:
        raise ValueError(f"{events.name}: holds no events, so no exposure is covered") from err
    coverage = measure_coverage(t_first, t_last, len(events), exposures, k)
    return coverage.kept, resolve_coverage(coverage, exposures, names, selected, events.name, hint)


def check_sensor_matches(events_name: str, sensor_size: Tuple[int, int], frame_name: str, frame_shape: Sequence[int]) -> None:
    """Raise ValueError naming both files when the event sensor and the frames differ in size."""
    if tuple(sensor_size) != tuple(frame_shape[:2]):
        raise ValueError(
            f"sensor size mismatch: {events_name} has a {sensor_size[1]}x{sensor_size[0]} (width x height) sensor "
            f"but the frame {frame_name} is {frame_shape[1]}x{frame_shape[0]}"
        )


# ----------------------------------------------------------------------------------------------
# Given poses


def _intrinsics_from_json(meta: dict, path: Path) -> Intrinsics:
    """Intrinsics from a nerfstudio/Blender-style transforms.json (fl_x.. or camera_angle_x)."""
    try:
        w, h = int(meta["w"]), int(meta["h"])
    except KeyError as err:
        raise ValueError(f"{path}: missing image size field {err.args[0]!r}") from None
    if "fl_x" in meta:
        fl_x = float(meta["fl_x"])
        fl_y = float(meta.get("fl_y", fl_x))
    elif "camera_angle_x" in meta:
        fl_x = fl_y = 0.5 * w / float(np.tan(0.5 * float(meta["camera_angle_x"])))
    else:
        raise ValueError(f"{path}: no focal length (fl_x or camera_angle_x)")
    return Intrinsics(w, h, fl_x, fl_y, float(meta.get("cx", w / 2.0)), float(meta.get("cy", h / 2.0)))


def read_calibration(path: Path, frame_size: Tuple[int, int]) -> Intrinsics:
    """A camera calibration JSON (see InputConfig.intrinsics) rescaled to frames of `frame_size`.

    Args:
        path: the JSON file.
        frame_size: (height, width) of the capture's frames after any downscaling.

    Raises:
        FileNotFoundError / ValueError: missing file, bad JSON, missing fields, or an aspect ratio
            that differs from the frames' (a calibration of another camera or crop).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: camera calibration file not found")
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: expected a JSON object with w, h and fl_x")
    intrinsics = _intrinsics_from_json(meta, path)
    if min(intrinsics.width, intrinsics.height) <= 0 or min(intrinsics.fl_x, intrinsics.fl_y) <= 0:
        raise ValueError(f"{path}: image size and focal lengths must be positive, got {intrinsics}")
    height, width = frame_size
    calib_aspect, frame_aspect = intrinsics.width / intrinsics.height, width / height
    if abs(calib_aspect / frame_aspect - 1.0) > CALIBRATION_ASPECT_TOLERANCE:
        raise ValueError(
            f"{path}: calibrated for {intrinsics.width}x{intrinsics.height} images, but the frames are "
            f"{width}x{height} (another aspect ratio: a calibration of another camera or crop?)"
        )
    return intrinsics.resized(width, height)


def poses_from_transforms(path: Path, exposures: Sequence[Exposure], k: int, frame_size: Tuple[int, int]) -> GivenPoses:
    """Per-latent poses from a transforms.json for the given exposures.

    Frames carrying ``time_us`` are interpolated at every latent time (exact where the times
    coincide); otherwise the frames must carry ``blurry_index`` (the exposure's ``frame``) and
    ``latent_index`` < k for every latent.

    Args:
        path: transforms.json with "frames" of c2w ``transform_matrix`` (OpenGL axes).
        exposures: the n selected exposures.
        k: latents per exposure.
        frame_size: (height, width) of the capture's frames, to rescale the intrinsics.

    Raises:
        FileNotFoundError: no such file.
        ValueError: malformed file, or a latent without a pose (names it).
    """
    if not path.is_file():
        raise FileNotFoundError(f"{path}: given-poses file not found")
    meta = json.loads(path.read_text())
    frames = meta.get("frames")
    if not frames:
        raise ValueError(f"{path}: no 'frames' list")
    intrinsics = _intrinsics_from_json(meta, path).resized(frame_size[1], frame_size[0])
    c2w = np.zeros((len(exposures), k, 4, 4))
    if all("time_us" in f for f in frames):
        times = np.array([int(f["time_us"]) for f in frames], dtype=np.int64)
        order = np.argsort(times, kind="stable")
        times, index = np.unique(times[order], return_index=True)
        known = np.array([frames[order[i]]["transform_matrix"] for i in index], dtype=np.float64)
        for i, e in enumerate(exposures):
            c2w[i] = interpolate_poses(times, known, latent_times_us(e.start_us, e.end_us, k))
    else:
        table = {(int(f["blurry_index"]), int(f["latent_index"])): f["transform_matrix"] for f in frames}
        for i, e in enumerate(exposures):
            for j in range(k):
                if (e.frame, j) not in table:
                    raise ValueError(f"{path}: no pose for frame {e.frame} latent {j} (and no time_us to interpolate)")
                c2w[i, j] = np.asarray(table[(e.frame, j)], dtype=np.float64)
    return GivenPoses(c2w=c2w, intrinsics=intrinsics, source=str(path))


# ----------------------------------------------------------------------------------------------
# Input forms


def _finish_capture(
    form: str,
    source: str,
    frames: List[np.ndarray],
    names: List[str],
    exposures: List[Exposure],
    events: Optional[EventSource],
    events_name: str,
    config: InputConfig,
    k: int,
    selected: List[int],
    notes: Sequence[str] = (),
    hint: str = COVERAGE_HINT,
) -> Capture:
    """Check the frames against the events, drop the frames they do not cover, downscale both, build the Capture."""
    shape = frames[0].shape
    for frame, name in zip(frames, names):
        if frame.shape != shape:
            raise ValueError(f"{name}: frame is {frame.shape[1]}x{frame.shape[0]} but {names[0]} is {shape[1]}x{shape[0]}")
    notes = list(notes)
    dropped: List[int] = []
    if events is not None:
        check_sensor_matches(events_name, events.sensor_size, names[0], shape)
        kept, coverage_notes = cover_frames(events, exposures, names, selected, k, hint)
        notes += coverage_notes
        dropped = [selected[i] for i in range(len(selected)) if i not in set(kept)]
        frames, names = [frames[i] for i in kept], [names[i] for i in kept]
        exposures, selected = [exposures[i] for i in kept], [selected[i] for i in kept]
        if config.downscale > 1:
            events = DownscaledEventSource(events, config.downscale)
    frames = [downscale_image(f, config.downscale) for f in frames]
    return Capture(
        form=form,
        source=source,
        frames=frames,
        frame_names=names,
        exposures=exposures,
        events=events,
        binned_events=None,
        event_count_scale=1.0 / config.downscale**2,
        selected=selected,
        dropped=dropped,
        notes=notes,
    )


def load_aedat4(config: InputConfig, k: int) -> Capture:
    """Input form (a): frames, exposures and events of one AEDAT4 recording."""
    path = Path(config.aedat4)
    events, aps = read_aedat4(path, None if config.events_time_unit == AUTO_UNIT else config.events_time_unit)
    if not aps:
        raise ValueError(f"{path}: no APS frames in the recording; edygs-process needs the blurry frames")
    indices = select_indices(len(aps), config, str(path))
    names = [f"{path.name} frame {i}" for i in indices]
    frames, depth_note = frames_to_rgb8([aps[i].image for i in indices], names, resolve_alpha_background(config),
                                        config.frame_bits)
    notes = [f"{path}: {depth_note}"] if depth_note else []
    exposures = []
    for i in indices:
        start, end = aps[i].exposure_start_us, aps[i].exposure_end_us
        if end <= start:
            raise ValueError(f"{path}: frame {i} has exposure end {end} µs not after its start {start} µs")
        exposures.append(Exposure(frame=i, start_us=int(start), end_us=int(end), file=path))
    check_exposure_sequence(exposures, str(path))
    source = ArrayEventSource(events, name=str(path))
    capture = _finish_capture("aedat4", str(path), frames, names, exposures, source, str(path), config, k, indices,
                              notes, AEDAT4_COVERAGE_HINT)
    capture.input_paths = [path]
    return capture


def load_exposure_table(config: InputConfig, k: int) -> Capture:
    """Input form (b): an exposure table naming the frames, and an event file."""
    csv_path = Path(config.exposures)
    if config.events is None:
        raise ValueError(f"{csv_path}: --exposures needs --events (the event file of the same capture)")
    all_exposures = read_exposures(csv_path)
    if not all_exposures:
        raise ValueError(f"{csv_path}: the exposure table lists no frame")
    indices = select_indices(len(all_exposures), config, str(csv_path))
    exposures = [all_exposures[i] for i in indices]
    names = [str(e.file) for e in exposures]
    frames, depth_note = read_frames([e.file for e in exposures], resolve_alpha_background(config), config.frame_bits)
    notes = [f"{csv_path}: {depth_note}"] if depth_note else []
    events = _open_events(Path(config.events), frames[0].shape[:2], config.events_t_offset_us, config.events_time_unit,
                          exposures, notes)
    try:
        capture = _finish_capture(
            "exposures", str(csv_path), frames, names, exposures, events, str(config.events), config, k, indices, notes
        )
    except Exception:
        events.close()
        raise
    raw_dir = csv_path.resolve().parent
    gt_dir = raw_dir / GT_DIR_NAME
    capture.gt_dir = gt_dir if gt_dir.is_dir() else None
    scene_json = raw_dir / SCENE_JSON_NAME
    capture.scene_json = scene_json if scene_json.is_file() else None
    capture.input_paths = [csv_path, Path(config.events)] + [e.file for e in exposures]
    return capture


def _e2nerf_exposures(n: int, files: Sequence[Path], exposure_us: int) -> List[Exposure]:
    """Exposures of ``exposure_us`` on the nominal E2NeRF clock (the format stores no timestamps)."""
    return [
        Exposure(frame=i, start_us=i * E2NERF_FRAME_PERIOD_US, end_us=i * E2NERF_FRAME_PERIOD_US + exposure_us, file=f)
        for i, f in zip(range(n), files)
    ]


def _read_scene_frames(
    folder: Path, files: Sequence[Path], config: InputConfig, notes: List[str], own_background: str = "white"
) -> List[np.ndarray]:
    """A scene's frames as uint8 RGB with one bit depth; the depth note (if any) joins ``notes``.

    ``own_background`` is the input's own convention, used unless --alpha-background is given.
    """
    frames, note = read_frames(files, resolve_alpha_background(config, own_background), config.frame_bits)
    if note:
        notes.append(f"{folder}: {note}")
    return frames


def load_e2nerf(config: InputConfig, k: int) -> Capture:
    """Input form (c): an E2NeRF synthetic (Blender) or real (LLFF) scene with binned events."""
    folder = Path(config.e2nerf)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: E2NeRF scene folder not found")
    if config.events_time_unit != AUTO_UNIT:
        raise ValueError(f"{folder}: --events-time-unit does not apply to --e2nerf (its events are pre-binned, without timestamps)")
    if E2NERF_BINS % (k - 1) != 0:
        raise ValueError(f"{folder}: E2NeRF stores {E2NERF_BINS} event bins per frame; k - 1 must divide it, got k={k}")
    notes: List[str] = []
    if (folder / e2nerf.TRAIN_TRANSFORMS).is_file():
        synthetic = e2nerf.read_synthetic(folder)
        files, events_file = synthetic.image_paths, synthetic.events_path
        frames = _read_scene_frames(folder, files, config, notes, E2NERF_ALPHA_BACKGROUND)
        h, w = frames[0].shape[:2]
        c2w, _ = synthetic.latent_poses(k)
        intrinsics, depth_range = synthetic.intrinsics(h, w), e2nerf.BLENDER_DEPTH_RANGE
        pose_file, exposure_us, theta, theta_origin = synthetic.meta_path, E2NERF_SYNTHETIC_EXPOSURE_US, None, ""
    elif (folder / e2nerf.POSES_BOUNDS_FILE).is_file():
        files = e2nerf.real_images(folder)
        frames = _read_scene_frames(folder, files, config, notes, E2NERF_ALPHA_BACKGROUND)
        h, w = frames[0].shape[:2]
        real = e2nerf.read_real(folder, E2NERF_BINS + 1, h, w, f"E2NeRF's {E2NERF_BINS} bins")
        c2w = real.c2w[:, :: E2NERF_BINS // (k - 1)]  # the latents at the merged bins' edges
        intrinsics, depth_range, events_file = real.intrinsics, real.depth_range, real.events_path
        pose_file, exposure_us = real.poses_path, E2NERF_REAL_EXPOSURE_US
        theta, theta_origin = E2NERF_REAL_THETA, "E2NeRF's real-data EDI value"
    else:
        raise FileNotFoundError(
            f"{folder}: neither {e2nerf.TRAIN_TRANSFORMS} (synthetic) nor {e2nerf.POSES_BOUNDS_FILE} (real) found"
        )
    bins = e2nerf.merge_bins(e2nerf.read_event_bins(events_file, len(frames), h, w, E2NERF_BINS), k, events_file)
    indices = select_indices(len(frames), config, str(folder))
    all_exposures = _e2nerf_exposures(len(frames), files, exposure_us)
    exposures = [all_exposures[i] for i in indices]
    names = [str(files[i]) for i in indices]
    capture = _finish_capture(
        "e2nerf", str(folder), [frames[i] for i in indices], names, exposures, None, "", config, k, indices, notes
    )
    capture.binned_events = downscale_counts(bins[indices], config.downscale)
    capture.event_count_scale = 1.0  # area averaging is already applied to the stored bins
    capture.default_theta, capture.default_theta_origin = theta, theta_origin
    capture.given_poses = GivenPoses(
        c2w=c2w[indices],
        intrinsics=intrinsics.resized(capture.width, capture.height),
        source=str(pose_file),
        depth_range=depth_range,
    )
    capture.input_paths = [pose_file, events_file] + [files[i] for i in indices]
    gt_dir = folder / GT_DIR_NAME  # ground truth in the raw-capture format (preprocess.e2nerf_writer)
    capture.gt_dir = gt_dir if (gt_dir / GT_TRANSFORMS_NAME).is_file() else None
    return capture


def load_evdeblurnerf(config: InputConfig, k: int) -> Capture:
    """Input form (c): an EvDeblurNeRF scene: blurry frames with exposures, raw events, a camera path."""
    from edygs_ns.preprocess.evdeblurnerf import EVENTS_FILE, TIMESTAMPS_FILE, read_evdeblurnerf_folder

    unit = config.evdeblurnerf_events_unit
    if config.events_time_unit != AUTO_UNIT:
        if config.events_time_unit not in ("us", "ns"):
            raise ValueError(f"{config.evdeblurnerf}: EvDeblurNeRF events are in us or ns, got --events-time-unit "
                             f"{config.events_time_unit}")
        unit = config.events_time_unit
    scene = read_evdeblurnerf_folder(
        Path(config.evdeblurnerf), unit, config.evdeblurnerf_timestamps_unit, config.evdeblurnerf_coordinates
    )
    indices = select_indices(len(scene.blurry), config, str(scene.root))
    exposures = scene.exposures(indices)
    names = [str(e.file) for e in exposures]
    notes: List[str] = []
    frames = _read_scene_frames(scene.root, [e.file for e in exposures], config, notes)
    if scene.events_unit_detected:
        notes.append(f"{scene.root / EVENTS_FILE}: event timestamps read in {scene.events_unit} (auto-detected from "
                     "the spans of the events and the images; --events-time-unit overrides)")
    events = scene.open_events()
    hint = (f"check {EVENTS_FILE} and {TIMESTAMPS_FILE}; the events were read in {scene.events_unit}"
            + (" (detected)" if scene.events_unit_detected else "")
            + ": see --events-time-unit and --evdeblurnerf-timestamps-unit")
    try:
        shape = frames[0].shape
        for frame, name in zip(frames, names):
            if frame.shape != shape:
                raise ValueError(f"{name}: frame is {frame.shape[1]}x{frame.shape[0]} but {names[0]} is {shape[1]}x{shape[0]}")
        kept, coverage_notes = cover_frames(events, exposures, names, indices, k, hint)
        dropped = [indices[i] for i in range(len(indices)) if i not in set(kept)]
        frames, names = [frames[i] for i in kept], [names[i] for i in kept]
        exposures, indices = [exposures[i] for i in kept], [indices[i] for i in kept]
        capture = _finish_capture(
            "evdeblurnerf", str(scene.root), frames, names, exposures, None, "", config, k, indices, notes + coverage_notes
        )
        capture.dropped = dropped
    except Exception:
        events.close()
        raise
    capture.events = DownscaledEventSource(events, config.downscale) if config.downscale > 1 else events
    capture.default_theta, capture.default_theta_origin = scene.default_theta, scene.default_theta_origin
    capture.given_poses = GivenPoses(
        c2w=scene.latent_poses(exposures, k),
        intrinsics=scene.intrinsics.resized(capture.width, capture.height),
        source=scene.path_source,
        depth_range=scene.depth_range,
    )
    if scene.sharp:
        capture.sharp_views = SharpViews(
            image_paths=[scene.image_paths[i] for i in scene.sharp],
            c2w=scene.image_c2w[scene.sharp],
            times_us=scene.mid_us[scene.sharp],
            intrinsics=scene.intrinsics,
        )
    capture.input_paths = scene.source_files()
    return capture


def load_capture(config: InputConfig, k: int, want_given_poses: bool) -> Capture:
    """Read one input form into a Capture and check it.

    Args:
        config: which input and which frames.
        k: latents per blurry frame (the E2NeRF bins are merged to k - 1; given poses are
            looked up or interpolated per latent).
        want_given_poses: load the poses of the input (``--poses given``).

    Returns:
        The capture; close it when done (it may hold an open event file).

    Raises:
        FileNotFoundError / ValueError: missing or inconsistent inputs, named in the message.
    """
    forms = [name for name in ("aedat4", "exposures", "e2nerf", "evdeblurnerf") if getattr(config, name) is not None]
    if len(forms) != 1:
        raise ValueError(
            "give exactly one input: --aedat4 FILE, or --exposures CSV --events FILE, or --e2nerf DIR, "
            "or --evdeblurnerf DIR "
            f"(got {', '.join('--' + f for f in forms) or 'none'})"
        )
    if config.events is not None and forms[0] != "exposures":
        raise ValueError(f"--events {config.events} goes with --exposures only (--{forms[0]} carries its own events)")
    if k < 2:
        raise ValueError(f"k must be at least 2 (one event bin), got {k}")
    loader = {"aedat4": load_aedat4, "exposures": load_exposure_table, "e2nerf": load_e2nerf,
              "evdeblurnerf": load_evdeblurnerf}[forms[0]]
    capture = loader(config, k)
    try:
        _attach_calibration(capture, config)
    except Exception:
        capture.close()
        raise
    if want_given_poses:
        try:
            _attach_given_poses(capture, config, k)
        except Exception:
            capture.close()
            raise
    return capture


def calibration_path(config: InputConfig) -> Optional[Path]:
    """The calibration file of the input: --intrinsics, else camera.json beside an exposure table."""
    if config.intrinsics is not None:
        return Path(config.intrinsics)
    if config.exposures is not None:
        beside = Path(config.exposures).resolve().parent / CALIBRATION_NAME
        if beside.is_file():
            return beside
    return None


def _attach_calibration(capture: Capture, config: InputConfig) -> None:
    """Set capture.calibration from calibration_path(config), or the intrinsics an E2NeRF /
    EvDeblurNeRF scene carries."""
    path = calibration_path(config)
    if path is not None:
        capture.calibration = read_calibration(path, (capture.height, capture.width))
        capture.calibration_source = str(path)
        capture.input_paths.append(path)
    elif capture.given_poses is not None:
        capture.calibration = capture.given_poses.intrinsics
        capture.calibration_source = capture.given_poses.source


def _attach_given_poses(capture: Capture, config: InputConfig, k: int) -> None:
    """Set capture.given_poses from --given-poses, the raw capture's gt/, or the E2NeRF / EvDeblurNeRF poses."""
    frame_size = (capture.height, capture.width)
    if config.given_poses is not None:
        capture.given_poses = poses_from_transforms(Path(config.given_poses), capture.exposures, k, frame_size)
        capture.input_paths.append(Path(config.given_poses))
    elif capture.given_poses is None and capture.gt_dir is not None and (capture.gt_dir / GT_TRANSFORMS_NAME).is_file():
        path = capture.gt_dir / GT_TRANSFORMS_NAME
        capture.given_poses = poses_from_transforms(path, capture.exposures, k, frame_size)
        capture.input_paths.append(path)
    if capture.given_poses is None:
        raise ValueError(
            f"{capture.source}: --poses given needs poses, but this input carries none "
            "(AEDAT4 recordings never do); pass --given-poses transforms.json or use --poses colmap"
        )

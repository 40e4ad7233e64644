"""The one reader of EvDeblurNeRF scenes, behind ``edygs-process --evdeblurnerf`` and the dataparser's
``evdeblurnerf`` layout (Cannici & Scaramuzza, CVPR 2024, "Mitigating Motion Blur in Neural Radiance
Fields with Events and Frames"; datasets Ev-DeblurNeRF-Blender and -CDAVIS).

Folder, as the authors publish it (uzh-rpg/EvDeblurNeRF, README.md "Folder structure")::

    images_1/00.png, 01.png, ...   every image of the scene, blurry AND sharp, in name order
    images_1/timestamps.npz        per image: timestamps, timestamps_start, timestamps_end
                                   (also start, end; not used here)
    poses_bounds.npy               one LLFF row per image (17 numbers)
    events.h5                      datasets x, y, t, p at the root
    all_poses_bounds.npy           optional: denser LLFF poses of the camera path ...
    all_timestamps.npy             ... and their instants, for interpolation
    ev_map.npz                     CDAVIS only: events carry rectified (floating-point) coordinates

What the authors' code establishes (repo uzh-rpg/EvDeblurNeRF, files named):

- Images: ``data/loader.py`` (``load_images``) lists the files of ``images`` + ``_<factor>``
  ending in png/jpg/JPG in sorted name order; both published configs use ``factor = 1``, and
  ``data/loader_events.py`` always reads ``images_1/timestamps.npz``. We read ``images_1/``.
- ``poses_bounds.npy`` has one row per image (``load_poses_raw`` asserts it): a 3x5 matrix
  [R | t | hwf] flattened row-major, then near and far. Rotation columns are LLFF's
  (down, right, back); the loader reorders them to (right, up, back) as E2NeRF's real layout
  does (``llff_to_opengl``). Focal length from hwf, principal point at the image centre
  (``load_intrinsics``).
- Sharp held-out views sit in the same folder; the README says they have
  ``timestamps_start == timestamps_end``. The maintainer (issue #11) adds that Blender scenes
  hold a sharp view every 8th image (``llffhold = 8``) and CDAVIS scenes append them at the
  end (``llffhold = 5`` with ``llffhold_end``). We split by the timestamps, not by position.
- Units are not stored in the files. ``options.py``: ``events_tms_unit`` (events.h5) defaults
  to ns and ``events_tms_files_unit`` (timestamps.npz, all_timestamps.npy) to µs; the Blender
  configs say ns / us and the CDAVIS configs us / us. So the event unit is detected (see
  :func:`detect_events_unit`) unless given, and the timestamp files default to µs.
- ``events.h5`` (``utils/events.py``, ``load_events_h5``): root datasets x, y, t, p; no sensor
  size (the image size is used). Polarity in {0, 1} or {-1, +1} (``load_event_data`` maps 0
  to -1). Coordinates are integers, or floats after rectification, and then ``ev_map.npz`` is
  present (``load_event_data`` asserts both ways). For the EDI prior the authors splat float
  coordinates bilinearly over the four neighbouring pixels; so do we, for the event bins that
  feed EDI and the event loss alike (``coordinates="bilinear"``, the default; shares outside the
  image are dropped, the undistortion moves some corner pixels out of the frame). Their event
  loss assigns an event to pixel (round(y), round(x)); ``coordinates="round"`` does that for
  every use (events that round outside the image are dropped).
- CDAVIS events come from a colour DAVIS: ``load_event_data`` gives each event pixel one
  colour of an RGGB Bayer pattern (R at even row and column, B at odd row and column). EDyGS
  models grey events, so each pixel's events are used as a grey log-intensity change (an
  approximation; see docs/layouts.md).
- Contrast thresholds in the configs: 0.2 (Blender), 0.25 (CDAVIS). Default theta here: the
  same, by scene kind (:func:`default_theta`: 0.25 when ``ev_map.npz`` marks a CDAVIS scene).
- Poses between known instants: the authors slerp the rotations of ``all_poses_bounds.npy``
  over ``all_timestamps.npy`` and interpolate the translations with a cubic ``interp1d``
  (clamped to their range). We do the same at every latent instant (rotations slerped,
  centres on a not-a-knot cubic spline, :func:`~edygs_ns.geometry.interpolate_poses`;
  linear with fewer than 4 known instants); without those files the per-image poses at
  ``timestamps`` are the known instants.

Exposure of blurry image i: [timestamps_start[i], timestamps_end[i]] (rounded to µs). Latent
times are evenly spaced over it (docs/layouts.md); normalised times span the first to the last
latent. Sharp views become the scene's novel views (ground truth), at their own instant.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import numpy as np

from edygs_ns.io.images import image_size
from edygs_ns.events.accumulate import latent_times_us
from edygs_ns.events.exposures import Exposure
from edygs_ns.events.readers import TICKS_PER_US, EventSource, H5EventSource
from edygs_ns.geometry import Intrinsics, interpolate_poses
from edygs_ns.preprocess import llff

#: Folder of the images (the authors' loader: "images" + "_" + factor, factor 1).
IMAGES_FOLDER = "images_1"
#: Per-image timestamps, inside IMAGES_FOLDER.
TIMESTAMPS_FILE = "timestamps.npz"
#: Keys of TIMESTAMPS_FILE this reader needs: pose instant, exposure start, exposure end.
TIMESTAMP_KEYS = ("timestamps", "timestamps_start", "timestamps_end")
#: Who needs the files (missing-file errors).
NEEDED_BY = "an EvDeblurNeRF scene"
#: One LLFF row per image.
POSES_BOUNDS_FILE = "poses_bounds.npy"
#: Optional dense camera path and its instants.
ALL_POSES_FILE = "all_poses_bounds.npy"
ALL_TIMESTAMPS_FILE = "all_timestamps.npy"
#: The event file.
EVENTS_FILE = "events.h5"
#: Present when events carry rectified (floating-point) coordinates (CDAVIS).
RECTIFICATION_MAP_FILE = "ev_map.npz"
#: Image suffixes the authors' loader takes (compared as written: png, jpg, JPG).
IMAGE_SUFFIXES = (".png", ".jpg", ".JPG")
#: Units an event or timestamp file may use.
TIME_UNITS = tuple(TICKS_PER_US)
#: Defaults for training on such a scene. Contrast threshold of the authors' Blender configs,
#: and of their CDAVIS configs (scenes with rectified events, ev_map.npz).
DEFAULT_THETA = 0.2
DEFAULT_THETA_CDAVIS = 0.25
#: How rectified (floating-point) event coordinates become pixels: "bilinear" (the authors' EDI
#: prior; default) or "round" (nearest pixel, their event loss).
COORDINATE_MODES = ("bilinear", "round")
DEFAULT_COORDINATES = "bilinear"
#: Camera-path translations are interpolated as the authors do (cubic interp1d).
PATH_TRANSLATION = "cubic"


def is_evdeblurnerf(root: Path) -> bool:
    """An EvDeblurNeRF scene has poses_bounds.npy, events.h5 and images_1/timestamps.npz."""
    return (
        (root / POSES_BOUNDS_FILE).is_file()
        and (root / EVENTS_FILE).is_file()
        and (root / IMAGES_FOLDER / TIMESTAMPS_FILE).is_file()
    )


@dataclass
class EvDeblurNeRFScene:
    """An EvDeblurNeRF folder, read and checked (times in µs on the event clock).

    Attributes:
        root: the scene folder.
        image_paths: I images of images_1/, name order (blurry and sharp).
        start_us, end_us, mid_us: [I] int64 exposure start, end and pose instant of each image.
        image_c2w: [I, 4, 4] OpenGL camera-to-world of each image (poses_bounds.npy).
        intrinsics: pinhole camera at the stored image size.
        depth_range: (near, far) over poses_bounds.npy, in its world units.
        path_times_us: [M] strictly increasing instants of the known camera path.
        path_c2w: [M, 4, 4] poses at those instants.
        path_source: the file(s) the camera path came from.
        events_path: events.h5.
        events_unit: "us" or "ns", the unit of events.h5's t.
        events_unit_detected: True when events_unit was detected rather than given.
        rectified_events: True when ev_map.npz is present (float coordinates; a CDAVIS scene).
        coordinates: how float coordinates become pixels, "bilinear" or "round" (COORDINATE_MODES).
    """

    root: Path
    image_paths: List[Path]
    start_us: np.ndarray
    end_us: np.ndarray
    mid_us: np.ndarray
    image_c2w: np.ndarray
    intrinsics: Intrinsics
    depth_range: Tuple[float, float]
    path_times_us: np.ndarray
    path_c2w: np.ndarray
    path_source: str
    events_path: Path
    events_unit: str
    events_unit_detected: bool
    rectified_events: bool
    coordinates: str = DEFAULT_COORDINATES

    @property
    def default_theta(self) -> float:
        """The authors' contrast threshold for this kind of scene (0.25 CDAVIS, 0.2 Blender)."""
        return DEFAULT_THETA_CDAVIS if self.rectified_events else DEFAULT_THETA

    @property
    def default_theta_origin(self) -> str:
        """Where default_theta comes from, for messages."""
        kind = "CDAVIS" if self.rectified_events else "Blender"
        return f"EvDeblurNeRF's {kind} configs"

    @property
    def blurry(self) -> List[int]:
        """Indices (into image_paths) of the blurry frames: exposure end after start."""
        return [int(i) for i in np.flatnonzero(self.end_us > self.start_us)]

    @property
    def sharp(self) -> List[int]:
        """Indices of the sharp held-out views: exposure start == end."""
        return [int(i) for i in np.flatnonzero(self.end_us == self.start_us)]

    def exposures(self, indices: Optional[Sequence[int]] = None) -> List[Exposure]:
        """Exposures of blurry frames (default: all); ``frame`` numbers them in the blurry list."""
        blurry = self.blurry
        chosen = range(len(blurry)) if indices is None else indices
        return [
            Exposure(frame=int(b), start_us=int(self.start_us[blurry[b]]), end_us=int(self.end_us[blurry[b]]),
                     file=self.image_paths[blurry[b]])
            for b in chosen
        ]

    def poses_at(self, times_us: np.ndarray) -> np.ndarray:
        """[Q, 4, 4] poses on the camera path at the given µs (rotations slerped, centres on a cubic
        spline as the authors interpolate; clamped to the path's range)."""
        return interpolate_poses(self.path_times_us, self.path_c2w, np.asarray(times_us), translation=PATH_TRANSLATION)

    def latent_poses(self, exposures: Sequence[Exposure], k: int) -> np.ndarray:
        """[n, k, 4, 4] pose of every latent instant of the exposures."""
        times = np.stack([latent_times_us(e.start_us, e.end_us, k) for e in exposures])
        return self.poses_at(times.reshape(-1)).reshape(len(exposures), k, 4, 4)

    def open_events(self) -> EventSource:
        """events.h5 as a windowed source in µs at the image size (caller closes it)."""
        return H5EventSource(
            self.events_path,
            (self.intrinsics.height, self.intrinsics.width),
            None,
            time_unit=self.events_unit,
            round_coordinates=self.rectified_events,
            bilinear=self.rectified_events and self.coordinates == "bilinear",
        )

    def source_files(self) -> List[Path]:
        """Every file the scene's content depends on (for fingerprints and caches)."""
        names = [POSES_BOUNDS_FILE, EVENTS_FILE, ALL_POSES_FILE, ALL_TIMESTAMPS_FILE, RECTIFICATION_MAP_FILE]
        files = [self.root / n for n in names if (self.root / n).is_file()]
        return files + [self.root / IMAGES_FOLDER / TIMESTAMPS_FILE] + list(self.image_paths)


# ----------------------------------------------------------------------------------------------
# Reading the folder


def _to_us(values: np.ndarray, unit: str) -> np.ndarray:
    """Times in ``unit`` as int64 µs (rounded)."""
    return np.round(np.asarray(values, dtype=np.float64) / TICKS_PER_US[unit]).astype(np.int64)


def _read_timestamps(path: Path, n_images: int, unit: str) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mid, start, end) int64 µs per image from timestamps.npz, checked against the image count."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: image timestamps not found")
    try:
        with np.load(path, allow_pickle=False) as data:
            found = sorted(data.files)
            missing = [k for k in TIMESTAMP_KEYS if k not in found]
            if missing:
                raise ValueError(f"{path}: missing key(s) {missing}; found {found}")
            arrays = {k: np.asarray(data[k]) for k in TIMESTAMP_KEYS}
    except (OSError, ValueError) as err:
        if str(path) in str(err):
            raise
        raise ValueError(f"{path}: cannot read as .npz ({err})") from err
    for key, values in arrays.items():
        if values.shape != (n_images,):
            raise ValueError(f"{path}: {key!r} has shape {values.shape}, expected ({n_images},): one entry per image")
        if values.dtype.kind not in "iuf" or not np.all(np.isfinite(values.astype(np.float64))):
            raise ValueError(f"{path}: {key!r} must hold finite numbers")
    mid, start, end = (_to_us(arrays[k], unit) for k in TIMESTAMP_KEYS)
    return mid, start, end


def _camera_path(
    root: Path, mid_us: np.ndarray, image_c2w: np.ndarray, unit: str
) -> Tuple[np.ndarray, np.ndarray, str]:
    """Known (instants, poses) of the camera path: all_poses_bounds.npy or the per-image poses."""
    all_poses, all_times = root / ALL_POSES_FILE, root / ALL_TIMESTAMPS_FILE
    if all_poses.is_file() != all_times.is_file():
        present, absent = (all_poses, all_times) if all_poses.is_file() else (all_times, all_poses)
        raise FileNotFoundError(f"{absent}: not found, but {present.name} is present (they go together)")
    if all_poses.is_file():
        rows = llff.read_rows(all_poses, None, "", NEEDED_BY)
        times = llff.load_npy(all_times, NEEDED_BY).reshape(-1)
        if times.shape[0] != rows.shape[0]:
            raise ValueError(f"{all_times}: {times.shape[0]} instants for the {rows.shape[0]} rows of {all_poses.name}")
        times_us = _to_us(times, unit)
        c2w = llff.rows_to_c2w(rows)
        source = f"{all_poses} + {all_times.name}"
    else:
        times_us, c2w, source = mid_us, image_c2w, f"{root / POSES_BOUNDS_FILE} at {TIMESTAMPS_FILE}'s timestamps"
    order = np.argsort(times_us, kind="stable")
    times_us, first = np.unique(times_us[order], return_index=True)
    return times_us, c2w[order][first], source


def detect_events_unit(events_span: float, reference_span_us: float) -> str:
    """The unit ("us" or "ns") under which the events last about as long as the frames.

    The event stream and the images cover roughly the same time; read in the wrong unit the
    events would last 1000 times too long (ns read as µs) or too short. The unit whose event
    span is closest (by ratio) to the frames' span wins.

    Args:
        events_span: last minus first event timestamp, in the file's ticks.
        reference_span_us: span of the image timestamps (and camera path), µs.
    """
    if events_span <= 0 or reference_span_us <= 0:
        return "us"
    distance = {u: abs(np.log(events_span / TICKS_PER_US[u] / reference_span_us)) for u in TIME_UNITS}
    return min(TIME_UNITS, key=lambda u: distance[u])


def read_evdeblurnerf_folder(
    root: Path, events_unit: str = "auto", timestamps_unit: str = "us", coordinates: str = DEFAULT_COORDINATES
) -> EvDeblurNeRFScene:
    """Read and check an EvDeblurNeRF scene folder (no pixels read, no events binned).

    Args:
        root: the scene folder.
        events_unit: unit of events.h5's t: "us", "ns", or "auto" (detected from the spans).
        timestamps_unit: unit of timestamps.npz and all_timestamps.npy ("us", the authors' default).
        coordinates: rectified (float) event coordinates are splatted "bilinear" (default, as the
            authors' EDI prior) or rounded ("round"); integer coordinates are unaffected.

    Raises:
        FileNotFoundError: the folder or a required file is missing (named).
        ValueError: a file disagrees with the images or is malformed (named, with what is wrong).
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: EvDeblurNeRF scene folder not found")
    if events_unit not in TIME_UNITS + ("auto",):
        raise ValueError(f"events unit must be 'auto' or one of {TIME_UNITS}, got {events_unit!r}")
    if timestamps_unit not in TIME_UNITS:
        raise ValueError(f"timestamps unit must be one of {TIME_UNITS}, got {timestamps_unit!r}")
    if coordinates not in COORDINATE_MODES:
        raise ValueError(f"event coordinates mode must be one of {COORDINATE_MODES}, got {coordinates!r}")
    folder = root / IMAGES_FOLDER
    images = sorted(p for p in folder.iterdir() if p.suffix in IMAGE_SUFFIXES) if folder.is_dir() else []
    if not images:
        raise FileNotFoundError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)}); an EvDeblurNeRF scene keeps them there")
    height, width = image_size(images[0])
    for path in images[1:]:
        if image_size(path) != (height, width):
            other = image_size(path)
            raise ValueError(f"{path}: image is {other[1]}x{other[0]} but {images[0].name} is {width}x{height}")

    mid, start, end = _read_timestamps(folder / TIMESTAMPS_FILE, len(images), timestamps_unit)
    backwards = np.flatnonzero(end < start)
    if len(backwards):
        i = int(backwards[0])
        raise ValueError(
            f"{folder / TIMESTAMPS_FILE}: image {images[i].name} ends its exposure ({end[i]} µs) before it starts "
            f"({start[i]} µs)"
        )
    if not np.any(end > start):
        raise ValueError(f"{folder / TIMESTAMPS_FILE}: no blurry image (every timestamps_start equals timestamps_end)")

    poses_file = root / POSES_BOUNDS_FILE
    rows = llff.read_rows(poses_file, len(images), f"one per image of {IMAGES_FOLDER}/", NEEDED_BY)
    intrinsics = llff.rows_intrinsics(rows, height, width)
    if not intrinsics.fl_x > 0:
        raise ValueError(f"{poses_file}: the focal length in the hwf column must be positive, got {intrinsics.fl_x}")
    image_c2w = llff.rows_to_c2w(rows)
    path_times, path_c2w, path_source = _camera_path(root, mid, image_c2w, timestamps_unit)

    events_path = root / EVENTS_FILE
    if not events_path.is_file():
        raise FileNotFoundError(f"{events_path}: event file not found")
    rectified = (root / RECTIFICATION_MAP_FILE).is_file()
    detected = events_unit == "auto"
    if detected:
        with H5EventSource(events_path, (height, width), None, round_coordinates=rectified) as raw:
            t_first, t_last = raw.t_range()  # in the file's ticks (read as µs)
        known = np.concatenate([start, end, path_times])
        events_unit = detect_events_unit(float(t_last - t_first), float(known.max() - known.min()))
    return EvDeblurNeRFScene(
        root=root,
        image_paths=images,
        start_us=start,
        end_us=end,
        mid_us=mid,
        image_c2w=image_c2w,
        intrinsics=intrinsics,
        depth_range=llff.rows_depth_range(rows),
        path_times_us=path_times,
        path_c2w=path_c2w,
        path_source=path_source,
        events_path=events_path,
        events_unit=events_unit,
        events_unit_detected=detected,
        rectified_events=rectified,
        coordinates=coordinates,
    )

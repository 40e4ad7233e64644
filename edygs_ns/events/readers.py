"""Read event files of the formats users have, into EventArray or a windowed EventSource.

Formats (dispatch on the file suffix):

- HDF5 (``.h5``, ``.hdf5``): datasets ``x, y, t, p`` at the root (EvDeblurNeRF style and our
  own writer) or in the group ``events/`` (DSEC style) with a root ``t_offset`` (dataset or
  attribute, µs) added to t. Sensor size from the attribute ``sensor_size`` = (height, width)
  on the root or the group, or attributes ``height`` and ``width``. t is in µs unless
  :class:`H5EventSource` is told otherwise (EvDeblurNeRF's Blender scenes store ns), and
  floating-point (rectified) coordinates can be rounded to the nearest pixel there, or splatted
  bilinearly over the four pixels around them (weighted entries, :class:`EventArray`).
- NumPy (``.npz``: arrays x, y, t, p and optionally sensor_size; ``.npy``: a structured array
  with fields x, y, t, p). t in µs. Pickled objects are never loaded (unpickling an untrusted
  file can run code).
- Text (``.txt``, ``.csv``): one ``t x y p`` per line, t in seconds, p in {0, 1}; ``#`` lines
  are skipped, and a header line ``sensor_size (height width): H W`` (our writer's) gives the
  sensor size. A first line holding exactly two integers is read as ``width height`` (the
  ETH/RPG dataset convention).
- AEDAT4 (``.aedat4``, PyPI ``aedat``): the first event stream and every frame (APS) packet.

:func:`open_event_source` gives windowed access for files larger than memory: HDF5 and .npy
windows are found by binary search on the timestamps and only the window is read; the whole
timestamp column is checked once, chunk by chunk, for order and NaN/inf when the file is opened.
:meth:`EventSource.chunks` hands a window out at most READ_CHUNK_EVENTS events at a time (each
chunk checked as it is read, errors naming the file and the event's index), which is how
edygs-process bins events: its memory does not grow with the file or with one exposure's events
(benchmarks/event_memory.py).

Every reader takes a ``time_unit`` (:mod:`edygs_ns.events.units`: s, ms, us, ns); None is the
format's documented unit (:func:`native_time_unit`).
"""

from __future__ import annotations

import re
import warnings
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple, Union

import numpy as np

from edygs_ns.events.types import EventArray
from edygs_ns.events.units import check_time_unit, ticks_to_us
from edygs_ns.events.validate import check_sensor_size, validate_events

PathLike = Union[str, Path]
SensorSize = Tuple[int, int]

HDF5_SUFFIXES = (".h5", ".hdf5")
NPZ_SUFFIXES = (".npz",)
NPY_SUFFIXES = (".npy",)
TEXT_SUFFIXES = (".txt", ".csv")
AEDAT4_SUFFIXES = (".aedat4",)
#: Names of the event columns in every format that stores them by name.
EVENT_FIELDS = ("x", "y", "t", "p")
#: DSEC keeps its events in this HDF5 group.
H5_EVENTS_GROUP = "events"
#: DSEC's offset (µs) added to the group's timestamps, a root dataset or attribute.
H5_T_OFFSET = "t_offset"
#: HDF5 attribute holding (height, width).
H5_SENSOR_SIZE_ATTR = "sensor_size"
#: HDF5 chunk cache per open dataset; larger than one chunk of our writer so probes hit the cache.
H5_CHUNK_CACHE_BYTES = 16 << 20
#: A timestamp binary search stops probing single elements once the range is this short and
#: reads it in one piece.
SEARCH_BLOCK_EVENTS = 1 << 16
#: Microseconds per second (text files store seconds).
US_PER_SECOND = 1_000_000
#: Our text writer's header line with the sensor size: "sensor_size (height width): H W".
TXT_SENSOR_SIZE_PATTERN = re.compile(r"sensor_size[^:]*:\s*(\d+)\s+(\d+)")
#: Columns of a text event line: t x y p.
TXT_COLUMNS = 4
#: Timestamp units an EvDeblurNeRF HDF5 file may use, as ticks per microsecond.
TICKS_PER_US = {"us": 1, "ns": 1000}
#: Events per chunk of the whole-file order and NaN/inf scan of a windowed source.
SCAN_CHUNK_EVENTS = 1 << 22
#: Most events :meth:`EventSource.chunks` hands out at once: the unit binning works in, so memory
#: is bounded by it, not by the file or by how many events one exposure window holds (reading,
#: checking and binning take ~50 bytes per event: ~50 MiB at 2^20; benchmarks/event_memory.py).
READ_CHUNK_EVENTS = 1 << 20
#: aedat frame formats and the number of channels kept (RGBA drops alpha); aedat >= 2.3 yields
#: 16-bit grey frames as "I;16" (uint16 codes, e.g. a DAVIS's 10-bit ADC values).
AEDAT_FRAME_FORMATS = {"L": 1, "RGB": 3, "RGBA": 3, "I;16": 1}


@dataclass(frozen=True)
class ApsFrame:
    """One intensity (APS) frame of a DAVIS recording.

    Attributes:
        image: [H, W] (grey) or [H, W, 3] (RGB) pixels as the sensor read them: uint8, or uint16
            codes for "I;16" frames (scaled to 8 bits by the caller, which sees every frame).
        exposure_start_us: start of the exposure in µs, on the event clock.
        exposure_end_us: end of the exposure in µs, on the event clock.
    """

    image: np.ndarray
    exposure_start_us: int
    exposure_end_us: int


def _resolve_sensor_size(
    from_file: Optional[Sequence[int]], from_caller: Optional[Sequence[int]], path: Path
) -> SensorSize:
    """The sensor size: the file's when it stores one, else the caller's, else an error."""
    source = str(path)
    file_size = check_sensor_size(from_file, source) if from_file is not None else None
    caller_size = check_sensor_size(from_caller, source) if from_caller is not None else None
    if file_size is not None and caller_size is not None and file_size != caller_size:
        raise ValueError(
            f"{source}: the file stores sensor_size (height, width) = {file_size} but {caller_size} was passed"
        )
    size = file_size or caller_size
    if size is None:
        raise ValueError(f"{source}: the file does not store the sensor size; pass sensor_size=(height, width)")
    return size


class EventSource(ABC):
    """Time-windowed access to the events of one file (or array).

    Use as a context manager, or call :meth:`close`, to release the file.
    """

    def __init__(self, name: str, sensor_size: SensorSize) -> None:
        self.name = name
        self.sensor_size: SensorSize = sensor_size

    @abstractmethod
    def __len__(self) -> int:
        """Number of events in the source."""

    @abstractmethod
    def t_range(self) -> Tuple[int, int]:
        """(t_first, t_last) in µs, the first and last event's timestamps.

        Raises:
            ValueError: the source holds no events.
        """

    @abstractmethod
    def window(self, t_start_us: int, t_end_us: int) -> EventArray:
        """Events with t_start_us <= t < t_end_us (validated), read without the rest of the file."""

    @abstractmethod
    def read_all(self) -> EventArray:
        """Every event of the source, validated as a whole."""

    def chunks(self, t_start_us: int, t_end_us: int, max_events: int = READ_CHUNK_EVENTS) -> Iterator[EventArray]:
        """The events with t_start_us <= t < t_end_us, in time order, at most ``max_events`` at a time.

        This default cuts :meth:`window` (sources in memory); file sources read each chunk alone.
        """
        events = self.window(t_start_us, t_end_us)
        for i0 in range(0, len(events), _chunk_size(max_events)):
            yield events.select(slice(i0, i0 + _chunk_size(max_events)))

    def close(self) -> None:
        """Release the underlying file (no-op for in-memory sources)."""

    def __enter__(self) -> "EventSource":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _no_events(self) -> ValueError:
        return ValueError(f"{self.name}: holds no events")


class ArrayEventSource(EventSource):
    """An EventSource over an EventArray already in memory."""

    def __init__(self, events: EventArray, name: str = "<in-memory events>") -> None:
        super().__init__(name, events.sensor_size)
        self.events = events

    def __len__(self) -> int:
        return len(self.events)

    def t_range(self) -> Tuple[int, int]:
        if len(self.events) == 0:
            raise self._no_events()
        return int(self.events.t[0]), int(self.events.t[-1])

    def window(self, t_start_us: int, t_end_us: int) -> EventArray:
        return self.events.time_slice(t_start_us, t_end_us)

    def read_all(self) -> EventArray:
        return self.events


def _chunk_size(max_events: int) -> int:
    """A chunk length of at least one event (``max_events`` <= 0: unlimited)."""
    return int(max_events) if max_events > 0 else np.iinfo(np.int64).max


def _first_index_at_or_after(
    value: int, n: int, item: Callable[[int], int], block: Callable[[int, int], np.ndarray]
) -> int:
    """Smallest i with t[i] >= value over a sorted column read through ``item`` / ``block``.

    Probes single elements until the candidate range is at most SEARCH_BLOCK_EVENTS long,
    then reads that range in one piece; touches O(log n) elements plus one block.
    """
    lo, hi = 0, n
    while hi - lo > SEARCH_BLOCK_EVENTS:
        mid = (lo + hi) // 2
        if item(mid) < value:
            lo = mid + 1
        else:
            hi = mid
    return lo + int(np.searchsorted(block(lo, hi), value, side="left"))


def _first_unsorted(t: np.ndarray, previous: Optional[float]) -> Optional[int]:
    """Index in ``t`` of the first timestamp below its predecessor (``previous`` before t[0]), or None."""
    if previous is not None and len(t) and t[0] < previous:
        return 0
    drops = np.flatnonzero(np.diff(t) < 0)
    return int(drops[0]) + 1 if len(drops) else None


#: Bilinear corners of a sub-pixel event: (dx, dy) offsets from (floor x, floor y).
BILINEAR_CORNERS = ((0, 0), (1, 0), (0, 1), (1, 1))


def splat_bilinear(
    x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray, sensor_size: SensorSize, source: str
) -> EventArray:
    """Sub-pixel events as weighted entries at the four pixels around each (bilinear splatting).

    Pixel centres sit at integer coordinates (as rounding assumes): an event at (3.25, 7.0)
    gives 0.75 of itself to pixel (3, 7) and 0.25 to (4, 7). Shares that land outside the
    sensor, and zero shares, are dropped; entries stay in time order (four per event at most).

    Args:
        x, y: [E] float pixel coordinates (column, row).
        t: [E] µs; p: [E] polarity ({0, 1} or {-1, +1}).
        sensor_size: (height, width).
        source: the file, for messages.

    Returns:
        EventArray with integer x, y and ``weight`` [E'] float32 in (0, 1].
    """
    xf, yf = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    x0, y0 = np.floor(xf), np.floor(yf)
    fx, fy = xf - x0, yf - y0
    shares = {(0, 0): (1 - fx) * (1 - fy), (1, 0): fx * (1 - fy), (0, 1): (1 - fx) * fy, (1, 1): fx * fy}
    xs = np.stack([x0 + dx for dx, _ in BILINEAR_CORNERS], axis=1).reshape(-1)
    ys = np.stack([y0 + dy for _, dy in BILINEAR_CORNERS], axis=1).reshape(-1)
    ws = np.stack([shares[c] for c in BILINEAR_CORNERS], axis=1).reshape(-1)
    height, width = sensor_size
    keep = (ws > 0) & (xs >= 0) & (xs < width) & (ys >= 0) & (ys < height)
    repeat = len(BILINEAR_CORNERS)
    ts, ps = np.repeat(np.asarray(t), repeat)[keep], np.repeat(np.asarray(p), repeat)[keep]
    events = validate_events(xs[keep], ys[keep], ts, ps, sensor_size, source)
    return EventArray(events.x, events.y, events.t, events.p, events.sensor_size, ws[keep].astype(np.float32))


class _ColumnEventSource(EventSource):
    """Windowed reads from four sorted on-disk columns (HDF5 datasets or memory-mapped fields).

    Opening scans the whole timestamp column (and floating-point coordinates) once, in chunks of
    SCAN_CHUNK_EVENTS, for NaN/inf and for timestamps that decrease: a binary search over an
    unsorted column would silently miss events.

    Args:
        name: the file, for messages.
        sensor_size: (height, width).
        columns: x, y, t, p column objects (sliceable, sorted by t).
        t_offset_us: µs added to every timestamp (after unit conversion).
        time_unit: unit of the stored t (one of :data:`edygs_ns.events.units.TIME_UNITS`).
        round_coordinates: accept floating-point (rectified) x, y: round them to the nearest
            pixel and drop events that land outside the sensor; otherwise coordinates must be
            whole numbers inside the sensor.
        bilinear: with round_coordinates, splat each event over the four pixels around (x, y)
            instead (pixel centres at integers; weights (1 - fx)(1 - fy), fx(1 - fy), ...; shares
            that fall outside the sensor are dropped): :func:`splat_bilinear`.

    Raises:
        ValueError: mismatched column lengths, NaN/inf, unsorted timestamps or an unreadable
            (corrupt) chunk; the message names the file.
    """

    def __init__(
        self,
        name: str,
        sensor_size: SensorSize,
        columns: Dict[str, Any],
        t_offset_us: int,
        time_unit: str = "us",
        round_coordinates: bool = False,
        bilinear: bool = False,
    ) -> None:
        super().__init__(name, sensor_size)
        self._columns = columns
        self._t_offset = int(t_offset_us)
        self._unit = check_time_unit(time_unit, name)
        self._round = bool(round_coordinates)
        self._bilinear = bool(bilinear) and self._round
        lengths = {k: int(v.shape[0]) for k, v in columns.items()}
        if len(set(lengths.values())) != 1:
            raise ValueError(f"{name}: event fields have mismatched lengths {lengths}")
        self._n = lengths["t"]
        self._scan()

    def __len__(self) -> int:
        return self._n

    def _slice(self, field: str, i0: int, i1: int) -> np.ndarray:
        """Stored values of one column, a read error (a corrupt chunk) named in one line."""
        try:
            return np.asarray(self._columns[field][i0:i1])
        except (OSError, RuntimeError, KeyError) as err:
            raise ValueError(
                f"{self.name}: cannot read event field {field!r} at events {i0}..{i1} ({err}); the file is corrupt or truncated"
            ) from None

    def _scan(self) -> None:
        """Check the whole file, chunk by chunk: finite t (and float x, y), t never decreasing."""
        previous: Optional[float] = None
        float_fields = [f for f in EVENT_FIELDS if np.dtype(self._columns[f].dtype).kind == "f"]
        for i0 in range(0, self._n, SCAN_CHUNK_EVENTS):
            i1 = min(i0 + SCAN_CHUNK_EVENTS, self._n)
            chunk = {f: self._slice(f, i0, i1) for f in float_fields}
            for field, values in chunk.items():
                bad = ~np.isfinite(values)
                if bad.any():
                    first = i0 + int(np.flatnonzero(bad)[0])
                    raise ValueError(
                        f"{self.name}: event field {field!r} holds NaN/inf (first at event index {first}: "
                        f"{values[first - i0]}); remove or repair those events"
                    )
            t = chunk["t"] if "t" in chunk else self._slice("t", i0, i1)
            drop = _first_unsorted(t, previous)
            if drop is not None:
                index = i0 + drop
                before = previous if drop == 0 else t[drop - 1]
                raise ValueError(
                    f"{self.name}: timestamps are not sorted: t decreases from {before} to {t[drop]} "
                    f"({self._unit}) at event index {index}; edygs_ns needs events in time order (sort the file by t)"
                )
            if len(t):
                previous = t[-1]

    def _t_at(self, i: int) -> int:
        return int(ticks_to_us(self._slice("t", i, i + 1), self._unit)[0])

    def _t_block(self, i0: int, i1: int) -> np.ndarray:
        return ticks_to_us(self._slice("t", i0, i1), self._unit).astype(np.int64)

    def _index(self, t_us: int) -> int:
        # The conversion to µs never decreases, so a search over converted values is exact.
        return _first_index_at_or_after(int(t_us) - self._t_offset, self._n, self._t_at, self._t_block)

    def t_range(self) -> Tuple[int, int]:
        if self._n == 0:
            raise self._no_events()
        return self._t_at(0) + self._t_offset, self._t_at(self._n - 1) + self._t_offset

    def _read(self, i0: int, i1: int, source: str, index_offset: int = 0) -> EventArray:
        raw = {k: self._slice(k, i0, i1) for k in EVENT_FIELDS}
        t = ticks_to_us(raw["t"], self._unit)  # NaN stays NaN: validate_events names it
        t = t + self._t_offset if t.dtype.kind == "f" else t.astype(np.int64) + self._t_offset
        x, y, p = raw["x"], raw["y"], raw["p"]
        if self._bilinear:
            return splat_bilinear(x, y, t, p, self.sensor_size, source)
        if self._round:
            x, y = np.rint(x), np.rint(y)
            height, width = self.sensor_size
            inside = (x >= 0) & (x < width) & (y >= 0) & (y < height)
            if not inside.all():
                x, y, t, p = x[inside], y[inside], t[inside], p[inside]
                index_offset = 0  # entries dropped: positions no longer the file's
        return validate_events(x, y, t, p, self.sensor_size, source, index_offset)

    def window(self, t_start_us: int, t_end_us: int) -> EventArray:
        if t_end_us <= t_start_us:
            return EventArray.empty(self.sensor_size)
        i0, i1 = self._index(t_start_us), self._index(t_end_us)
        return self._read(i0, max(i0, i1), f"{self.name} (events {i0}..{i1})", index_offset=i0)

    def chunks(self, t_start_us: int, t_end_us: int, max_events: int = READ_CHUNK_EVENTS) -> Iterator[EventArray]:
        """The window's events read ``max_events`` at a time (binary search for its ends, then slices).

        Each chunk is checked as it is read (coordinates inside the sensor, polarity, order); an
        error names the file and the event's index in it.
        """
        if t_end_us <= t_start_us:
            return
        i0, i1 = self._index(t_start_us), self._index(t_end_us)
        step = _chunk_size(max_events)
        for a in range(i0, i1, step):
            b = min(a + step, i1)
            yield self._read(a, b, f"{self.name} (events {a}..{b})", index_offset=a)

    def read_all(self) -> EventArray:
        return self._read(0, self._n, self.name)


class H5EventSource(_ColumnEventSource):
    """Windowed reads from an HDF5 event file (root datasets or DSEC ``events/`` group).

    ``time_unit``, ``round_coordinates`` and ``bilinear`` are as for the column source (see its
    docstring).
    """

    def __init__(
        self,
        path: Path,
        sensor_size: Optional[Sequence[int]],
        t_offset_us: Optional[int],
        time_unit: str = "us",
        round_coordinates: bool = False,
        bilinear: bool = False,
    ) -> None:
        import h5py

        try:
            self._file = h5py.File(path, "r", rdcc_nbytes=H5_CHUNK_CACHE_BYTES)
        except OSError as err:
            raise ValueError(f"{path}: cannot open as HDF5 ({err})") from err
        try:
            group = self._locate_group(path)
            file_size = self._stored_sensor_size(group)
            if t_offset_us is None:
                t_offset_us = self._stored_t_offset(group)
            columns = {k: group[k] for k in EVENT_FIELDS}
            for k, dataset in columns.items():
                if dataset.ndim != 1:
                    raise ValueError(f"{path}: dataset {dataset.name!r} must be one-dimensional, got {dataset.shape}")
            super().__init__(
                str(path), _resolve_sensor_size(file_size, sensor_size, path), columns, t_offset_us,
                time_unit=time_unit, round_coordinates=round_coordinates, bilinear=bilinear,
            )
        except Exception:
            self._file.close()
            raise

    def _locate_group(self, path: Path) -> Any:
        import h5py

        f = self._file
        if all(k in f for k in EVENT_FIELDS):
            return f
        group = f.get(H5_EVENTS_GROUP)
        if isinstance(group, h5py.Group) and all(k in group for k in EVENT_FIELDS):
            return group
        raise ValueError(
            f"{path}: no event datasets {EVENT_FIELDS} at the root or in group '{H5_EVENTS_GROUP}/' "
            f"(root holds {sorted(f.keys())})"
        )

    def _stored_sensor_size(self, group: Any) -> Optional[Sequence[int]]:
        for holder in (self._file, group):
            if H5_SENSOR_SIZE_ATTR in holder.attrs:
                return np.asarray(holder.attrs[H5_SENSOR_SIZE_ATTR]).reshape(-1).tolist()
            if "height" in holder.attrs and "width" in holder.attrs:
                return [holder.attrs["height"], holder.attrs["width"]]
        return None

    def _stored_t_offset(self, group: Any) -> int:
        f = self._file
        if H5_T_OFFSET in f:
            return int(np.asarray(f[H5_T_OFFSET][()]).reshape(-1)[0])
        for holder in (f, group):
            if H5_T_OFFSET in holder.attrs:
                return int(np.asarray(holder.attrs[H5_T_OFFSET]).reshape(-1)[0])
        return 0

    def close(self) -> None:
        self._file.close()


class NpyEventSource(_ColumnEventSource):
    """Windowed reads from a memory-mapped structured .npy array with fields x, y, t, p."""

    def __init__(
        self, path: Path, array: np.memmap, sensor_size: Optional[Sequence[int]], t_offset_us: int, time_unit: str = "us"
    ) -> None:
        columns = {k: array[k] for k in EVENT_FIELDS}
        super().__init__(str(path), _resolve_sensor_size(None, sensor_size, path), columns, t_offset_us, time_unit=time_unit)
        self._array = array

    def close(self) -> None:
        self._columns = {}
        self._array = None  # type: ignore[assignment]


@dataclass
class _RawEvents:
    """Columns as a file stores them, before validation; sensor_size None when not stored."""

    x: np.ndarray
    y: np.ndarray
    t: np.ndarray
    p: np.ndarray
    sensor_size: Optional[Sequence[int]] = None


def _columns_from_mapping(mapping: Any, path: Path) -> _RawEvents:
    keys = list(mapping.keys())
    missing = [k for k in EVENT_FIELDS if k not in keys]
    if missing:
        raise ValueError(f"{path}: missing event field(s) {missing}; found {sorted(keys)}")
    size = mapping["sensor_size"] if "sensor_size" in keys else None
    return _RawEvents(*(np.asarray(mapping[k]) for k in EVENT_FIELDS), sensor_size=size)


def _load_npz(path: Path) -> _RawEvents:
    try:
        with np.load(path, allow_pickle=False) as data:
            return _columns_from_mapping({k: data[k] for k in data.files}, path)
    except (OSError, ValueError) as err:
        if str(path) in str(err):
            raise
        raise ValueError(f"{path}: cannot read as .npz ({err})") from err


#: What a refused pickled .npy should become instead.
PICKLE_REFUSED = (
    "holds pickled Python objects, which edygs_ns never loads (unpickling an untrusted file can run code); "
    "save the columns x, y, t, p as an .npz or as a structured .npy array"
)


def _load_npy(path: Path) -> _RawEvents:
    """A .npy holding a structured array with fields x, y, t, p (never a pickle)."""
    try:
        data = np.load(path, allow_pickle=False)
    except ValueError as err:
        if "allow_pickle" in str(err):
            raise ValueError(f"{path}: {PICKLE_REFUSED}") from None
        raise ValueError(f"{path}: cannot read as .npy ({err})") from None
    except OSError as err:
        raise ValueError(f"{path}: cannot read as .npy ({err})") from None
    if data.dtype.names is not None:
        return _columns_from_mapping({k: data[k] for k in data.dtype.names}, path)
    raise ValueError(
        f"{path}: expected a structured array with fields {EVENT_FIELDS}, "
        f"got an array of dtype {data.dtype} and shape {data.shape}"
    )


def _text_preamble(path: Path) -> Tuple[Optional[SensorSize], int, str]:
    """Scan the header: (sensor size if stated, lines to skip, delimiter or '' for whitespace)."""
    sensor_size: Optional[SensorSize] = None
    skip = 0
    with open(path, "r", encoding="utf-8", errors="replace") as f:
        for line in f:
            stripped = line.strip()
            if not stripped or stripped.startswith("#"):
                match = TXT_SENSOR_SIZE_PATTERN.search(stripped)
                if match:
                    sensor_size = (int(match.group(1)), int(match.group(2)))
                skip += 1
                continue
            delimiter = "," if "," in stripped else ""
            fields = stripped.split(delimiter or None)
            if len(fields) == 2 and all(s.strip().isdigit() for s in fields):
                width, height = (int(s) for s in fields)
                sensor_size = sensor_size or (height, width)
                skip += 1
            return sensor_size, skip, delimiter
    return sensor_size, skip, ""


def _load_text(path: Path) -> _RawEvents:
    sensor_size, skip, delimiter = _text_preamble(path)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*input contained no data")  # empty file: 0 events
            table = np.loadtxt(
                path, comments="#", delimiter=delimiter or None, skiprows=skip, ndmin=2, dtype=np.float64
            )
    except ValueError as err:
        raise ValueError(f"{path}: malformed event line ({err}); expected 't x y p' with t in seconds") from err
    if table.shape[0] == 0:
        table = np.zeros((0, TXT_COLUMNS))
    if table.shape[1] < TXT_COLUMNS:
        raise ValueError(f"{path}: expected {TXT_COLUMNS} columns 't x y p' per line, found {table.shape[1]}")
    return _RawEvents(table[:, 1], table[:, 2], table[:, 0], table[:, 3], sensor_size=sensor_size)


def _frame_from_packet(frame: Dict[str, Any], path: Path) -> ApsFrame:
    fmt = frame["format"]
    if fmt not in AEDAT_FRAME_FORMATS:
        raise ValueError(f"{path}: unsupported frame format {fmt!r} (supported: {sorted(AEDAT_FRAME_FORMATS)})")
    dtype = np.uint16 if fmt == "I;16" else np.uint8
    pixels = np.asarray(frame["pixels"])
    if pixels.dtype != dtype:
        raise ValueError(f"{path}: frame format {fmt!r} with {pixels.dtype} pixels (expected {np.dtype(dtype).name})")
    channels = AEDAT_FRAME_FORMATS[fmt]
    image = pixels.reshape(pixels.shape[:2]) if channels == 1 else pixels[..., :channels]
    return ApsFrame(
        image=np.ascontiguousarray(image),
        exposure_start_us=int(frame["exposure_begin_t"]),
        exposure_end_us=int(frame["exposure_end_t"]),
    )


def _load_aedat4(path: Path) -> Tuple[_RawEvents, List[ApsFrame]]:
    import aedat

    try:
        decoder = aedat.Decoder(path)
        streams = decoder.id_to_stream()
    except Exception as err:  # the Rust decoder raises its own exception types
        raise ValueError(f"{path}: cannot read as AEDAT4 ({err})") from err
    event_ids = sorted(i for i, s in streams.items() if s.get("type") == "events")
    if not event_ids:
        raise ValueError(f"{path}: no event stream (streams: {streams})")
    event_id = event_ids[0]
    packets: List[np.ndarray] = []
    frames: List[ApsFrame] = []
    try:
        for packet in decoder:
            if "events" in packet and packet["stream_id"] == event_id:
                packets.append(packet["events"])
            elif "frame" in packet:
                frames.append(_frame_from_packet(packet["frame"], path))
    except ValueError:
        raise
    except Exception as err:
        raise ValueError(f"{path}: corrupt AEDAT4 packet ({err})") from err
    if packets:
        ev = np.concatenate(packets)
        cols = (ev["x"], ev["y"], ev["t"], ev["on"])
    else:
        cols = (np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0, np.int64), np.zeros(0, np.int8))
    size = (streams[event_id]["height"], streams[event_id]["width"])
    return _RawEvents(*cols, sensor_size=size), frames


def _check_path(path: PathLike) -> Path:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: event file not found")
    return path


def native_time_unit(path: PathLike) -> str:
    """The timestamp unit a file's format documents: seconds for text files, µs otherwise."""
    return "s" if Path(path).suffix.lower() in TEXT_SUFFIXES else "us"


def _finish(
    raw: _RawEvents, path: Path, sensor_size: Optional[Sequence[int]], t_offset_us: Optional[int], time_unit: str
) -> EventArray:
    size = _resolve_sensor_size(raw.sensor_size, sensor_size, path)
    t = np.asarray(raw.t)
    if t.dtype.kind not in "iufb":
        raise ValueError(f"{path}: event field 't' has non-numeric dtype {t.dtype}")
    t = ticks_to_us(t, time_unit)
    if t_offset_us:
        t = t + (float(t_offset_us) if t.dtype.kind == "f" else int(t_offset_us))
    return validate_events(raw.x, raw.y, t, raw.p, size, str(path))


def _unknown_format(path: Path) -> ValueError:
    known = HDF5_SUFFIXES + NPZ_SUFFIXES + NPY_SUFFIXES + TEXT_SUFFIXES + AEDAT4_SUFFIXES
    return ValueError(f"{path}: unknown event file type {path.suffix!r} (known: {', '.join(known)})")


def open_event_source(
    path: PathLike,
    sensor_size: Optional[Sequence[int]] = None,
    t_offset_us: Optional[int] = None,
    time_unit: Optional[str] = None,
) -> EventSource:
    """Open an event file for windowed reads.

    HDF5 files and structured .npy arrays are read lazily (a window reads only its events; the
    timestamps are scanned once, chunk by chunk, for order and NaN/inf); the other formats are
    loaded whole, once, into memory and validated there.

    Args:
        path: the event file.
        sensor_size: (height, width), needed when the file does not store it.
        t_offset_us: µs added to every timestamp, replacing the file's own offset (DSEC
            ``t_offset``); None uses the file's offset, or 0 when it has none.
        time_unit: unit of the stored timestamps (s, ms, us, ns); None: the format's own
            (:func:`native_time_unit`).

    Returns:
        An EventSource; close it (or use ``with``) when done.

    Raises:
        FileNotFoundError: no such file.
        ValueError: unknown format, missing sensor size, or a malformed file (names the file).
    """
    path = _check_path(path)
    unit = check_time_unit(time_unit or native_time_unit(path), str(path))
    suffix = path.suffix.lower()
    if suffix in HDF5_SUFFIXES:
        return H5EventSource(path, sensor_size, t_offset_us, time_unit=unit)
    if suffix in NPY_SUFFIXES:
        try:
            mapped = np.load(path, mmap_mode="r", allow_pickle=False)
        except ValueError:
            mapped = None  # object arrays cannot be memory-mapped; read_events says why it refuses them
        if mapped is not None and mapped.dtype.names is not None and all(k in mapped.dtype.names for k in EVENT_FIELDS):
            return NpyEventSource(path, mapped, sensor_size, int(t_offset_us or 0), time_unit=unit)
    return ArrayEventSource(read_events(path, sensor_size, t_offset_us, unit), name=str(path))


def read_events(
    path: PathLike,
    sensor_size: Optional[Sequence[int]] = None,
    t_offset_us: Optional[int] = None,
    time_unit: Optional[str] = None,
) -> EventArray:
    """Read every event of a file (format chosen by suffix) into a validated EventArray.

    Args:
        path: .h5/.hdf5, .npz, .npy, .txt/.csv or .aedat4 event file.
        sensor_size: (height, width), needed when the file does not store it; must agree with
            the file's when it does.
        t_offset_us: µs added to every timestamp, replacing the file's own offset (DSEC
            ``t_offset``); None uses the file's offset, or 0 when it has none.
        time_unit: unit of the stored timestamps (s, ms, us, ns); None: the format's own
            (:func:`native_time_unit`).

    Returns:
        EventArray (x, y int32 pixels, t int64 µs, p int8 ±1), sorted by t.

    Raises:
        FileNotFoundError: no such file.
        ValueError: unknown format, missing sensor size, or bad events (names the file).
    """
    path = _check_path(path)
    unit = check_time_unit(time_unit or native_time_unit(path), str(path))
    suffix = path.suffix.lower()
    if suffix in HDF5_SUFFIXES:
        with H5EventSource(path, sensor_size, t_offset_us, time_unit=unit) as source:
            return source.read_all()
    loaders: Dict[Tuple[str, ...], Callable[[Path], _RawEvents]] = {
        NPZ_SUFFIXES: _load_npz,
        NPY_SUFFIXES: _load_npy,
        TEXT_SUFFIXES: _load_text,
        AEDAT4_SUFFIXES: lambda p: _load_aedat4(p)[0],
    }
    for suffixes, loader in loaders.items():
        if suffix in suffixes:
            return _finish(loader(path), path, sensor_size, t_offset_us, unit)
    raise _unknown_format(path)


def read_aedat4(path: PathLike, time_unit: Optional[str] = None) -> Tuple[EventArray, List[ApsFrame]]:
    """Read the events and APS frames of an AEDAT4 recording (DAVIS cameras).

    Args:
        path: .aedat4 file; the sensor size comes from its event stream.
        time_unit: unit of the event timestamps; None: µs, as the format defines. The frames'
            exposure times are converted with the same unit.

    Returns:
        (events, frames): the first event stream as an EventArray, and every frame packet as an
        ApsFrame with its exposure start/end (µs, on the event clock), in file order.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not an AEDAT4 file, no event stream, or bad events (names the file).
    """
    path = _check_path(path)
    unit = check_time_unit(time_unit or native_time_unit(path), str(path))
    raw, frames = _load_aedat4(path)
    if unit != "us":
        frames = [
            ApsFrame(f.image, int(ticks_to_us(np.array([f.exposure_start_us]), unit)[0]),
                     int(ticks_to_us(np.array([f.exposure_end_us]), unit)[0]))
            for f in frames
        ]
    return _finish(raw, path, None, None, unit), frames

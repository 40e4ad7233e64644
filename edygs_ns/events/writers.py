"""Write an EventArray to disk: HDF5 (the project's format), .npz and text.

The HDF5 layout is the one of docs/layouts.md: datasets ``x``, ``y`` (uint16, or int32 for
sensors wider than uint16), ``t`` (int64 µs), ``p`` (int8 ±1) at the root, and the root
attribute ``sensor_size = (height, width)``. Every writer refuses to replace an existing file
unless ``overwrite=True``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Optional, Tuple, Union

import numpy as np

from edygs_ns.events.types import EventArray

PathLike = Union[str, Path]

#: Events per HDF5 chunk (1 MiB of int64 timestamps); also the unit windowed reads work in.
H5_CHUNK_EVENTS = 1 << 17
#: gzip level of the HDF5 datasets (fast to write, ~3-5x smaller than raw for event streams).
H5_GZIP_LEVEL = 4
#: Largest coordinate stored as uint16; wider sensors get int32 coordinates.
UINT16_MAX = np.iinfo(np.uint16).max
#: Microseconds per second, for the text format's timestamps in seconds.
US_PER_SECOND = 1_000_000
#: Digits after the decimal point of text timestamps in seconds (1 µs resolution).
TXT_TIME_DECIMALS = 6
#: Header of the text format; the reader recognises the sensor_size line.
TXT_HEADER = "edygs_ns events: one event per line, t[s] x y p (p: 0=off, 1=on)\nsensor_size (height width): {h} {w}"


def _refuse_overwrite(path: Path, overwrite: bool) -> None:
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: file exists; pass overwrite=True to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)


def _coordinate_dtype(events: EventArray) -> np.dtype:
    return np.dtype(np.uint16) if max(events.sensor_size) - 1 <= UINT16_MAX else np.dtype(np.int32)


def write_events_h5(path: PathLike, events: EventArray, overwrite: bool = False) -> Path:
    """Write events to an HDF5 file with chunked, gzip-compressed datasets.

    The file is written under a temporary name and moved into place, so an interrupted write
    never leaves a half-written file at ``path``.

    Args:
        path: destination .h5 file.
        events: the E events to store.
        overwrite: replace ``path`` if it exists.

    Returns:
        The path written.

    Raises:
        FileExistsError: ``path`` exists and ``overwrite`` is False.
    """
    import h5py

    path = Path(path)
    _refuse_overwrite(path, overwrite)
    tmp = path.with_name(path.name + ".partial")
    coord = _coordinate_dtype(events)
    columns = {
        "x": events.x.astype(coord),
        "y": events.y.astype(coord),
        "t": events.t.astype(np.int64),
        "p": events.p.astype(np.int8),
    }
    with h5py.File(tmp, "w") as f:
        for name, values in columns.items():
            f.create_dataset(
                name,
                data=values,
                maxshape=(None,),
                chunks=(H5_CHUNK_EVENTS,),
                compression="gzip",
                compression_opts=H5_GZIP_LEVEL,
                shuffle=True,
            )
        f.attrs["sensor_size"] = np.asarray(events.sensor_size, dtype=np.int64)
    os.replace(tmp, path)
    return path


class H5EventWriter:
    """Write an HDF5 event file piece by piece (files larger than memory), in write_events_h5's layout.

    Events are appended in time order; the file is written under ``<path>.partial`` and moved into
    place when the writer closes without an error (an error or interruption removes the partial
    file and leaves ``path`` untouched).

    Args:
        path: destination .h5 file.
        sensor_size: (height, width) of every event appended.
        overwrite: replace ``path`` if it exists.

    Raises:
        FileExistsError: ``path`` exists and ``overwrite`` is False.
    """

    def __init__(self, path: PathLike, sensor_size: Tuple[int, int], overwrite: bool = False) -> None:
        import h5py

        self.path = Path(path)
        _refuse_overwrite(self.path, overwrite)
        self.sensor_size = (int(sensor_size[0]), int(sensor_size[1]))
        self._tmp = self.path.with_name(self.path.name + ".partial")
        coord = _coordinate_dtype(EventArray.empty(self.sensor_size))
        self._dtypes = {"x": coord, "y": coord, "t": np.dtype(np.int64), "p": np.dtype(np.int8)}
        self._file = h5py.File(self._tmp, "w")
        for name, dtype in self._dtypes.items():
            self._file.create_dataset(name, shape=(0,), dtype=dtype, maxshape=(None,), chunks=(H5_CHUNK_EVENTS,),
                                      compression="gzip", compression_opts=H5_GZIP_LEVEL, shuffle=True)
        self._file.attrs["sensor_size"] = np.asarray(self.sensor_size, dtype=np.int64)
        self._n = 0
        self._last_t: Optional[int] = None

    def __len__(self) -> int:
        return self._n

    def append(self, events: EventArray) -> None:
        """Add events (sorted by t, starting no earlier than the last one appended).

        Raises:
            ValueError: another sensor size, or events earlier than those already written.
        """
        if events.sensor_size != self.sensor_size:
            raise ValueError(f"{self.path}: appended events are from a {events.sensor_size} sensor, not {self.sensor_size}")
        if not len(events):
            return
        if self._last_t is not None and int(events.t[0]) < self._last_t:
            raise ValueError(f"{self.path}: appended events start at t = {int(events.t[0])} µs, before the last one "
                             f"written ({self._last_t} µs); append in time order")
        n0, n1 = self._n, self._n + len(events)
        for name, dtype in self._dtypes.items():
            dataset = self._file[name]
            dataset.resize((n1,))
            dataset[n0:n1] = getattr(events, name).astype(dtype, copy=False)
        self._n, self._last_t = n1, int(events.t[-1])

    def close(self, keep: bool = True) -> Path:
        """Finish the file and move it into place (``keep=False``: discard it)."""
        if self._file:
            self._file.close()
        if keep:
            os.replace(self._tmp, self.path)
        elif self._tmp.exists():
            self._tmp.unlink()
        return self.path

    def __enter__(self) -> "H5EventWriter":
        return self

    def __exit__(self, exc_type: Any, *exc: Any) -> None:
        self.close(keep=exc_type is None)


def write_events_npz(path: PathLike, events: EventArray, overwrite: bool = False) -> Path:
    """Write events to a compressed .npz with arrays x, y, t (µs), p (±1) and sensor_size.

    Args:
        path: destination .npz file.
        events: the E events to store.
        overwrite: replace ``path`` if it exists.

    Returns:
        The path written.

    Raises:
        FileExistsError: ``path`` exists and ``overwrite`` is False.
    """
    path = Path(path)
    _refuse_overwrite(path, overwrite)
    with open(path, "wb") as f:
        np.savez_compressed(
            f,
            x=events.x.astype(np.int32),
            y=events.y.astype(np.int32),
            t=events.t.astype(np.int64),
            p=events.p.astype(np.int8),
            sensor_size=np.asarray(events.sensor_size, dtype=np.int64),
        )
    return path


def write_events_txt(path: PathLike, events: EventArray, overwrite: bool = False) -> Path:
    """Write events as text: ``#`` header lines, then ``t x y p`` per line.

    t is in seconds with microsecond resolution and p is 0 (off) or 1 (on), the convention of
    the ETH/RPG and v2e text files. The header carries the sensor size.

    Args:
        path: destination .txt file.
        events: the E events to store.
        overwrite: replace ``path`` if it exists.

    Returns:
        The path written.

    Raises:
        FileExistsError: ``path`` exists and ``overwrite`` is False.
        ValueError: negative timestamps (the text format is written for t >= 0 only).
    """
    path = Path(path)
    if len(events) and int(events.t[0]) < 0:
        raise ValueError(f"{path}: cannot write negative timestamps (first t = {int(events.t[0])} µs) as text")
    _refuse_overwrite(path, overwrite)
    seconds = events.t // US_PER_SECOND
    micros = events.t % US_PER_SECOND
    on = (events.p > 0).astype(np.int64)
    # Integer seconds and microseconds are written separately so no float rounding creeps in.
    table = np.stack([seconds, micros, events.x.astype(np.int64), events.y.astype(np.int64), on], axis=1)
    header = TXT_HEADER.format(h=events.height, w=events.width)
    np.savetxt(path, table, fmt=f"%d.%0{TXT_TIME_DECIMALS}d %d %d %d", header=header, comments="# ")
    return path

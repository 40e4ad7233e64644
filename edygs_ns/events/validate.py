"""Turn raw event columns from any file into a checked EventArray.

Every reader funnels its columns through :func:`validate_events`, so each fault in a file is
reported the same way: a ``ValueError`` naming the file and what is wrong with it.
"""

from __future__ import annotations

from typing import Sequence, Tuple

import numpy as np

from edygs_ns.events.types import EventArray

#: How many offending values an error message quotes at most.
MAX_QUOTED = 5


def check_sensor_size(sensor_size: Sequence[int], source: str) -> Tuple[int, int]:
    """Check a (height, width) pair and return it as two Python ints.

    Args:
        sensor_size: (height, width) in pixels.
        source: name of the file (or other origin) quoted in error messages.

    Raises:
        ValueError: not two positive integers.
    """
    try:
        values = [v for v in np.asarray(sensor_size).reshape(-1).tolist()]
    except (TypeError, ValueError) as err:
        raise ValueError(f"{source}: sensor_size {sensor_size!r} is not (height, width)") from err
    if len(values) != 2 or any(float(v) != int(v) or int(v) <= 0 for v in values):
        raise ValueError(f"{source}: sensor_size {sensor_size!r} must be two positive integers (height, width)")
    return int(values[0]), int(values[1])


def _as_integer_column(values: np.ndarray, name: str, source: str, index_offset: int = 0) -> np.ndarray:
    """Cast a numeric column to int64, refusing non-finite or fractional values."""
    if values.dtype.kind == "b":
        return values.astype(np.int64)
    if values.dtype.kind not in "iuf":
        raise ValueError(f"{source}: event field {name!r} has non-numeric dtype {values.dtype}")
    if values.dtype.kind == "f":
        bad = ~np.isfinite(values)
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            raise ValueError(
                f"{source}: event field {name!r} holds {int(bad.sum())} NaN/inf value(s) "
                f"(first at event index {index_offset + first}: {values[first]})"
            )
        if name in ("x", "y"):
            frac = values != np.round(values)
            if frac.any():
                first = int(np.flatnonzero(frac)[0])
                raise ValueError(
                    f"{source}: event field {name!r} holds {int(frac.sum())} non-integer value(s) "
                    f"(first at event index {index_offset + first}: {values[first]})"
                )
        if name == "p":
            return values
        return np.round(values).astype(np.int64)
    return values.astype(np.int64, copy=False)


def _polarity_to_signed(p: np.ndarray, source: str, index_offset: int = 0) -> np.ndarray:
    """Map polarity in {0, 1} or {-1, +1} (any numeric dtype) to int8 {-1, +1}."""
    is_one = p == 1
    if (is_one | (p == 0)).all():
        return np.where(is_one, np.int8(1), np.int8(-1))
    if (is_one | (p == -1)).all():
        return p.astype(np.int8)
    found = np.unique(p).tolist()
    offending = [v for v in found if v not in (-1, 0, 1)] or found
    bad = np.isin(p, offending) if offending != found else (p == -1)
    where = f"; first at event index {index_offset + int(np.flatnonzero(bad)[0])}" if bad.any() else ""
    raise ValueError(
        f"{source}: polarity must be all in {{0, 1}} or all in {{-1, +1}}; found values "
        f"{found[: 2 * MAX_QUOTED]} (offending: {offending[:MAX_QUOTED]}{where})"
    )


def validate_events(
    x: np.ndarray,
    y: np.ndarray,
    t: np.ndarray,
    p: np.ndarray,
    sensor_size: Sequence[int],
    source: str,
    index_offset: int = 0,
) -> EventArray:
    """Check raw event columns and convert them into an EventArray.

    Args:
        x: [E] column in pixels (any integer dtype, or floats holding integers).
        y: [E] row in pixels.
        t: [E] timestamp in microseconds (floats are rounded to the nearest microsecond).
        p: [E] polarity, all in {0, 1} (0 becomes -1) or all in {-1, +1}.
        sensor_size: (height, width) in pixels.
        source: the file the columns came from, quoted in every error message.
        index_offset: position in the file of the first entry (a chunk read from the middle of a
            file): the event indices quoted in messages are the file's.

    Returns:
        EventArray with x, y int32, t int64 (µs), p int8 in {-1, +1}.

    Raises:
        ValueError: mismatched lengths, NaN/inf, coordinates outside the sensor, timestamps that
            decrease, or polarity values outside {0, 1} / {-1, +1}; the message names ``source``.
    """
    height, width = check_sensor_size(sensor_size, source)
    columns = {"x": np.asarray(x), "y": np.asarray(y), "t": np.asarray(t), "p": np.asarray(p)}
    for name, values in columns.items():
        if values.ndim != 1:
            raise ValueError(f"{source}: event field {name!r} must be one-dimensional, got shape {values.shape}")
    lengths = {name: len(values) for name, values in columns.items()}
    if len(set(lengths.values())) != 1:
        raise ValueError(f"{source}: event fields have mismatched lengths {lengths}")

    xi = _as_integer_column(columns["x"], "x", source, index_offset)
    yi = _as_integer_column(columns["y"], "y", source, index_offset)
    ti = _as_integer_column(columns["t"], "t", source, index_offset)
    pi = _as_integer_column(columns["p"], "p", source, index_offset)

    outside = (xi < 0) | (xi >= width) | (yi < 0) | (yi >= height)
    if outside.any():
        first = int(np.flatnonzero(outside)[0])
        raise ValueError(
            f"{source}: {int(outside.sum())} of {len(xi)} events lie outside the sensor "
            f"(height={height}, width={width}); e.g. event {index_offset + first} at x={xi[first]}, y={yi[first]}. "
            "Is sensor_size right?"
        )
    decreases = np.diff(ti) < 0
    if decreases.any():
        first = int(np.flatnonzero(decreases)[0])
        raise ValueError(
            f"{source}: timestamps are not monotonic: t decreases {int(decreases.sum())} time(s) "
            f"(first between event {index_offset + first} and {index_offset + first + 1}: {ti[first]} -> {ti[first + 1]} µs)"
        )
    p_signed = _polarity_to_signed(pi, source, index_offset)
    return EventArray(
        x=xi.astype(np.int32),
        y=yi.astype(np.int32),
        t=ti.astype(np.int64, copy=False),
        p=p_signed,
        sensor_size=(height, width),
    )

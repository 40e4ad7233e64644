"""Timestamp units of event files: conversion to microseconds, and detection from time spans.

Every event in edygs_ns carries t in µs (int64). Files store seconds (text files, often as
floats), milliseconds, microseconds (most HDF5/NumPy files, AEDAT4) or nanoseconds (some
simulators and EvDeblurNeRF's Blender scenes). A file does not say which, so the reader is told
(``--events-time-unit``) or the unit is detected: read in the right unit, the events last about
as long as the frames they come with; read in a wrong one, 1000 times longer or shorter.
"""

from __future__ import annotations

from typing import Dict, Tuple

import numpy as np

#: Microseconds per tick of each timestamp unit a file may use.
US_PER_TICK: Dict[str, float] = {"s": 1_000_000.0, "ms": 1_000.0, "us": 1.0, "ns": 0.001}
#: The units, coarsest first.
TIME_UNITS: Tuple[str, ...] = tuple(US_PER_TICK)
#: The option value that asks for detection.
AUTO_UNIT = "auto"


def check_time_unit(unit: str, source: str) -> str:
    """Return ``unit`` when it is one of TIME_UNITS, else raise ValueError naming ``source``."""
    if unit not in US_PER_TICK:
        raise ValueError(f"{source}: unknown time unit {unit!r}; expected one of {', '.join(TIME_UNITS)}")
    return unit


def ticks_to_us(values: np.ndarray, unit: str) -> np.ndarray:
    """Timestamps stored in ``unit`` as µs.

    Integer ticks of µs or finer are floored exactly (integer division); float ticks of µs or
    finer are floored; ticks coarser than a µs (s, ms) are rounded to the nearest µs, since a
    decimal fraction of a second is rarely exact in binary. NaN/inf stay NaN/inf (floats in,
    floats out) so the validation can name them.

    Args:
        values: [E] timestamps as stored (any numeric dtype).
        unit: one of TIME_UNITS.

    Returns:
        [E] int64 µs for integer input, float64 whole µs for float input.
    """
    values = np.asarray(values)
    factor = US_PER_TICK[unit]
    if values.dtype.kind == "f":
        if factor > 1:
            return np.round(values * factor)
        return np.floor(values / round(1.0 / factor))
    ticks = values.astype(np.int64, copy=False)
    if factor >= 1:
        return ticks * int(factor)
    return ticks // int(round(1.0 / factor))


def detect_time_unit(tick_span: float, reference_span_us: float, default: str) -> Tuple[str, str]:
    """The unit under which the events last about as long as the frames, and why.

    Args:
        tick_span: last minus first event timestamp, in the file's (unknown) ticks.
        reference_span_us: time the frames cover (first exposure start to last exposure end), µs.
        default: the file format's documented unit, kept when the spans cannot decide.

    Returns:
        (unit, reason): the chosen unit and a one-line explanation for the log.
    """
    if not (np.isfinite(tick_span) and tick_span > 0 and reference_span_us > 0):
        return default, f"kept {default} (the events or the exposures span no time, so the spans cannot decide)"
    distance = {u: abs(np.log(tick_span * US_PER_TICK[u] / reference_span_us)) for u in TIME_UNITS}
    unit = min(TIME_UNITS, key=lambda u: distance[u])
    seconds = reference_span_us / US_PER_TICK["s"]
    reason = (f"the events span {tick_span:.6g} ticks, {tick_span * US_PER_TICK[unit] / US_PER_TICK['s']:.3g} s in "
              f"{unit}, closest to the {seconds:.3g} s the exposures span")
    return unit, reason

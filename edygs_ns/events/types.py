"""The one in-memory event type of edygs_ns.

Units everywhere: x, y in pixels (column, row, origin top-left), t in microseconds (int64),
p in {-1, +1}. Arrays are numpy; events are always sorted by t.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

import numpy as np


@dataclass(frozen=True)
class EventArray:
    """E events from one sensor of size (height, width), sorted by timestamp.

    Attributes:
        x: [E] int32 column in pixels, 0 <= x < width.
        y: [E] int32 row in pixels, 0 <= y < height.
        t: [E] int64 timestamp in microseconds, non-decreasing.
        p: [E] int8 polarity in {-1, +1}.
        sensor_size: (height, width) in pixels.
    """

    x: np.ndarray
    y: np.ndarray
    t: np.ndarray
    p: np.ndarray
    sensor_size: Tuple[int, int]

    def __post_init__(self) -> None:
        n = len(self.t)
        for name in ("x", "y", "p"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"EventArray: field {name!r} has {len(getattr(self, name))} entries, t has {n}")

    def __len__(self) -> int:
        return int(len(self.t))

    @property
    def height(self) -> int:
        return int(self.sensor_size[0])

    @property
    def width(self) -> int:
        return int(self.sensor_size[1])

    @classmethod
    def empty(cls, sensor_size: Tuple[int, int]) -> "EventArray":
        """An array with no events for a sensor of (height, width)."""
        return cls(
            x=np.zeros(0, np.int32),
            y=np.zeros(0, np.int32),
            t=np.zeros(0, np.int64),
            p=np.zeros(0, np.int8),
            sensor_size=(int(sensor_size[0]), int(sensor_size[1])),
        )

    def time_slice(self, t_start_us: int, t_end_us: int) -> "EventArray":
        """Events with t_start_us <= t < t_end_us (binary search, no copy of the fields)."""
        i0, i1 = np.searchsorted(self.t, [t_start_us, t_end_us], side="left")
        return EventArray(self.x[i0:i1], self.y[i0:i1], self.t[i0:i1], self.p[i0:i1], self.sensor_size)

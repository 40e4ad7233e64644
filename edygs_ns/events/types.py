"""The one in-memory event type of edygs_ns.

Units everywhere: x, y in pixels (column, row, origin top-left), t in microseconds (int64),
p in {-1, +1}. Arrays are numpy; events are always sorted by t. An event may carry a weight
(its share of one event at that pixel): rectified, sub-pixel events splatted bilinearly over
their four neighbouring pixels become four weighted entries (see :meth:`EventArray.signed`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

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
        weight: [E] float32 share in (0, 1] of one event that each entry carries (bilinear
            splatting of sub-pixel coordinates), or None: every entry is one whole event.
    """

    x: np.ndarray
    y: np.ndarray
    t: np.ndarray
    p: np.ndarray
    sensor_size: Tuple[int, int]
    weight: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        n = len(self.t)
        for name in ("x", "y", "p") + (("weight",) if self.weight is not None else ()):
            if len(getattr(self, name)) != n:
                raise ValueError(f"EventArray: field {name!r} has {len(getattr(self, name))} entries, t has {n}")

    def signed(self) -> np.ndarray:
        """[E] float64 signed contribution of each entry: p, times its weight when there is one."""
        p = self.p.astype(np.float64)
        return p if self.weight is None else p * self.weight

    def select(self, index: np.ndarray) -> "EventArray":
        """The entries at ``index`` (a boolean mask, sorted integer indices or a slice), weights kept."""
        weight = self.weight[index] if self.weight is not None else None
        return EventArray(self.x[index], self.y[index], self.t[index], self.p[index], self.sensor_size, weight)

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
        weight = self.weight[i0:i1] if self.weight is not None else None
        return EventArray(self.x[i0:i1], self.y[i0:i1], self.t[i0:i1], self.p[i0:i1], self.sensor_size, weight)

"""A tiny raw capture written by hand (no simulator): textured frames, an exposure table, events, poses.

The frames are random texture shifted a few pixels per frame (a moving camera) or not at all (a
static one); the events are random, spread uniformly over ``event_span_us``; poses.json gives
poses with time_us, so ``--poses given --given-poses poses.json`` needs no COLMAP.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Tuple

import cv2
import numpy as np

from edygs_ns.events.exposures import Exposure, write_exposures
from edygs_ns.events.types import EventArray
from edygs_ns.events.writers import write_events_h5

#: Frame period and exposure of the tiny capture, µs.
PERIOD_US = 100_000
EXPOSURE_US = 80_000
#: Frame size (height, width).
SIZE = (24, 32)
#: Pixels the texture shifts per frame when the camera moves.
SHIFT_PX = 3
#: Events per frame period.
EVENTS_PER_PERIOD = 2000


@dataclass
class TinyCapture:
    """What write_tiny_capture wrote."""

    root: Path
    csv: Path
    events: Path
    poses: Path
    exposures: List[Exposure]


def textured_frames(n: int, size: Tuple[int, int] = SIZE, shift_px: int = SHIFT_PX, seed: int = 0) -> List[np.ndarray]:
    """n uint8 [H, W, 3] views of one smooth random texture, shifted by shift_px per frame."""
    rng = np.random.default_rng(seed)
    h, w = size
    big = cv2.GaussianBlur(rng.integers(0, 256, (h + 16, w + 16 + n * shift_px)).astype(np.float32), (0, 0), 1.5)
    big = cv2.normalize(big, None, 20, 235, cv2.NORM_MINMAX)
    views = [big[8: 8 + h, 8 + i * shift_px: 8 + i * shift_px + w] for i in range(n)]
    return [np.repeat(v.astype(np.uint8)[..., None], 3, axis=2) for v in views]


def write_tiny_capture(
    folder: Path,
    n: int = 4,
    shift_px: int = SHIFT_PX,
    event_span_us: Optional[Tuple[int, int]] = None,
    seed: int = 0,
) -> TinyCapture:
    """Write frames/, exposures.csv, events.h5 and poses.json into ``folder``.

    Args:
        folder: created.
        n: frames.
        shift_px: texture shift per frame (0: a static camera).
        event_span_us: (first, last) event time; default covers every exposure.
        seed: random seed.
    """
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "frames").mkdir(exist_ok=True)
    exposures = []
    for i, frame in enumerate(textured_frames(n, SIZE, shift_px, seed)):
        path = folder / "frames" / f"{i:04d}.png"
        cv2.imwrite(str(path), frame)
        exposures.append(Exposure(i, i * PERIOD_US, i * PERIOD_US + EXPOSURE_US, path))
    csv = write_exposures(folder / "exposures.csv", exposures, relative_to=folder)
    first, last = event_span_us or (0, (n - 1) * PERIOD_US + EXPOSURE_US)
    rng = np.random.default_rng(seed)
    count = EVENTS_PER_PERIOD * n
    t = np.sort(rng.integers(first, last + 1, count)).astype(np.int64)
    t[0], t[-1] = first, last
    events = EventArray(rng.integers(0, SIZE[1], count).astype(np.int32), rng.integers(0, SIZE[0], count).astype(np.int32),
                        t, rng.choice(np.array([-1, 1], np.int8), count), SIZE)
    write_events_h5(folder / "events.h5", events)
    frames = []
    for i in range(n):
        for t_us in (i * PERIOD_US, i * PERIOD_US + EXPOSURE_US):
            c2w = np.eye(4)
            c2w[0, 3] = 0.01 * shift_px * t_us / PERIOD_US
            frames.append({"time_us": t_us, "transform_matrix": c2w.tolist()})
    meta = {"w": SIZE[1], "h": SIZE[0], "fl_x": 30.0, "fl_y": 30.0, "cx": SIZE[1] / 2, "cy": SIZE[0] / 2, "frames": frames}
    (folder / "poses.json").write_text(json.dumps(meta))
    return TinyCapture(folder, csv, folder / "events.h5", folder / "poses.json", exposures)

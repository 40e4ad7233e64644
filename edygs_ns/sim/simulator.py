"""A standard event-camera simulator (the ESIM / v2e model), streaming over frames.

Each pixel keeps a reference log intensity L_ref, set from the first frame, with
log intensity L = log(I + log_eps). Between two consecutive frames L moves linearly in time;
every time it crosses L_ref + C (or L_ref - C) the pixel emits a +1 (or -1) event at the
interpolated crossing time and L_ref moves by +C (or -C) -- several events per step when the
change spans several thresholds. Per-pixel thresholds C are drawn once from N(C, sigma),
clipped to at least MIN_CONTRAST_THRESHOLD. An event closer than the refractory period to its
pixel's previous emitted event is dropped (its threshold crossing still moves L_ref: the change
is lost, as for a pixel held in reset). The work is vectorised over pixels; the only Python
loop runs over the crossing index (at most the largest number of crossings of one pixel in one
step), never over events.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional

import numpy as np

from edygs_ns.events.types import EventArray

#: Smallest per-pixel contrast threshold when thresholds are jittered.
MIN_CONTRAST_THRESHOLD = 0.01
#: Time of "no previous event" for the refractory check, µs.
NO_PREVIOUS_EVENT_US = np.iinfo(np.int64).min // 2


@dataclass
class SimulatorConfig:
    """Parameters of the event simulator."""

    contrast_threshold: float = 0.2
    """Mean contrast threshold C: change of log intensity per event."""
    threshold_sigma: float = 0.0
    """Standard deviation of the per-pixel thresholds (0: every pixel uses C exactly)."""
    refractory_us: int = 0
    """Events closer than this (µs) to their pixel's previous event are dropped (0: none)."""
    log_eps: float = 1e-3
    """Offset inside the log, L = log(I + log_eps), so that black pixels stay finite."""
    seed: int = 0
    """Seed of the threshold draw; equal seeds give equal events."""


class EventSimulator:
    """Streaming simulator: feed frames one at a time, get the events since the previous frame."""

    def __init__(self, height: int, width: int, config: Optional[SimulatorConfig] = None) -> None:
        """Set up a (height, width) sensor.

        Args:
            height: rows in pixels.
            width: columns in pixels.
            config: simulator parameters (defaults if None).

        Raises:
            ValueError: non-positive size or threshold, negative sigma or refractory period.
        """
        self.config = config or SimulatorConfig()
        cfg = self.config
        if height <= 0 or width <= 0:
            raise ValueError(f"EventSimulator: sensor size must be positive, got {height}x{width}")
        if cfg.contrast_threshold <= 0 or cfg.threshold_sigma < 0 or cfg.refractory_us < 0 or cfg.log_eps <= 0:
            raise ValueError(f"EventSimulator: invalid config {cfg}")
        self.sensor_size = (int(height), int(width))
        rng = np.random.default_rng(cfg.seed)
        if cfg.threshold_sigma > 0:
            c = rng.normal(cfg.contrast_threshold, cfg.threshold_sigma, size=height * width)
            self.thresholds = np.maximum(c, MIN_CONTRAST_THRESHOLD)
        else:
            self.thresholds = np.full(height * width, float(cfg.contrast_threshold))
        self._ref: Optional[np.ndarray] = None
        self._log_prev: Optional[np.ndarray] = None
        self._t_prev: Optional[int] = None
        self._last_event_t = np.full(height * width, NO_PREVIOUS_EVENT_US, dtype=np.int64)

    def log_intensity(self, intensity: np.ndarray) -> np.ndarray:
        """log(I + log_eps) of a [H, W] linear intensity image, flattened to [H*W] float64."""
        return np.log(intensity.astype(np.float64).reshape(-1) + self.config.log_eps)

    def _check_frame(self, intensity: np.ndarray, t_us: int) -> np.ndarray:
        intensity = np.asarray(intensity)
        if intensity.shape != self.sensor_size:
            raise ValueError(f"EventSimulator.feed: frame shape {intensity.shape} != sensor size {self.sensor_size}")
        if not np.all(np.isfinite(intensity)) or np.any(intensity < 0):
            raise ValueError("EventSimulator.feed: intensity must be finite and >= 0 (linear, grey)")
        if self._t_prev is not None and int(t_us) <= self._t_prev:
            raise ValueError(f"EventSimulator.feed: t_us {t_us} does not increase (previous frame at {self._t_prev})")
        return intensity

    def feed(self, intensity: np.ndarray, t_us: int) -> EventArray:
        """Advance to a new frame and return the events since the previous one.

        Args:
            intensity: [H, W] float linear grey intensity (>= 0).
            t_us: frame time in µs, greater than the previous frame's.

        Returns:
            Events with t in (t_prev, t_us], sorted by t (empty for the first frame, which only
            sets the reference).
        """
        intensity = self._check_frame(intensity, t_us)
        log_now = self.log_intensity(intensity)
        t_now = int(t_us)
        if self._ref is None or self._log_prev is None or self._t_prev is None:
            self._ref, self._log_prev, self._t_prev = log_now.copy(), log_now, t_now
            return EventArray.empty(self.sensor_size)
        events = self._step(self._log_prev, log_now, self._t_prev, t_now)
        self._log_prev, self._t_prev = log_now, t_now
        return events

    def _step(self, log_prev: np.ndarray, log_now: np.ndarray, t_prev: int, t_now: int) -> EventArray:
        """Events of one interval, log intensity moving linearly from log_prev to log_now."""
        assert self._ref is not None
        ref, c = self._ref, self.thresholds
        diff = log_now - ref
        # Crossings per pixel; the reference stays within one threshold of the log intensity.
        n_cross = np.floor(np.abs(diff) / c).astype(np.int64)
        pixels = np.flatnonzero(n_cross)
        if len(pixels) == 0:
            return EventArray.empty(self.sensor_size)
        sign = np.sign(diff[pixels])
        counts = n_cross[pixels]
        slope = log_now[pixels] - log_prev[pixels]
        ref_px, c_px, start_px = ref[pixels], c[pixels], log_prev[pixels]
        refractory = int(self.config.refractory_us)
        xs: List[np.ndarray] = []
        ts: List[np.ndarray] = []
        ps: List[np.ndarray] = []
        for i in range(1, int(counts.max()) + 1):
            active = np.flatnonzero(counts >= i)
            level = ref_px[active] + i * sign[active] * c_px[active]
            # A zero slope with a crossing only comes from rounding drift of the reference:
            # such events go to the end of the step instead of dividing by zero.
            s_act = slope[active]
            frac = np.divide(level - start_px[active], s_act, out=np.ones_like(level), where=s_act != 0)
            frac = np.clip(frac, 0.0, 1.0)
            t_ev = t_prev + np.round(frac * (t_now - t_prev)).astype(np.int64)
            pix = pixels[active]
            if refractory > 0:
                keep = t_ev - self._last_event_t[pix] >= refractory
                pix, t_ev, sgn = pix[keep], t_ev[keep], sign[active][keep]
            else:
                sgn = sign[active]
            self._last_event_t[pix] = t_ev
            xs.append(pix)
            ts.append(t_ev)
            ps.append(sgn)
        self._ref[pixels] = ref_px + sign * counts * c_px
        pix_all = np.concatenate(xs)
        t_all = np.concatenate(ts)
        p_all = np.concatenate(ps).astype(np.int8)
        order = np.argsort(t_all, kind="stable")
        width = self.sensor_size[1]
        return EventArray(
            x=(pix_all[order] % width).astype(np.int32),
            y=(pix_all[order] // width).astype(np.int32),
            t=t_all[order],
            p=p_all[order],
            sensor_size=self.sensor_size,
        )


def simulate_events(intensity: np.ndarray, times_us: np.ndarray, config: Optional[SimulatorConfig] = None) -> EventArray:
    """Events of a whole clip of frames (the first frame sets the reference).

    Args:
        intensity: [N, H, W] float linear grey intensity (>= 0).
        times_us: [N] int64 strictly increasing frame times, µs.
        config: simulator parameters (defaults if None).

    Returns:
        Events between times_us[0] and times_us[-1], sorted by t.

    Raises:
        ValueError: shapes disagree, or times do not increase.
    """
    intensity = np.asarray(intensity)
    times_us = np.asarray(times_us)
    if intensity.ndim != 3 or times_us.shape != (intensity.shape[0],):
        raise ValueError(f"simulate_events: need intensity [N, H, W] and times [N], got {intensity.shape} and {times_us.shape}")
    sim = EventSimulator(intensity.shape[1], intensity.shape[2], config)
    parts = [sim.feed(frame, int(t)) for frame, t in zip(intensity, times_us)]
    if not parts:
        return EventArray.empty((intensity.shape[1], intensity.shape[2]))
    return EventArray(
        x=np.concatenate([e.x for e in parts]),
        y=np.concatenate([e.y for e in parts]),
        t=np.concatenate([e.t for e in parts]),
        p=np.concatenate([e.p for e in parts]),
        sensor_size=sim.sensor_size,
    )

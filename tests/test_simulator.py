"""The event simulator against the log-intensity model, determinism, refractory period, streaming."""

from __future__ import annotations

import numpy as np
import pytest

from edygs_ns.events.accumulate import accumulate
from edygs_ns.sim.simulator import MIN_CONTRAST_THRESHOLD, EventSimulator, SimulatorConfig, simulate_events

H, W = 16, 20
N_FRAMES = 12
FRAME_DT_US = 1_000


def smooth_clip(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """[N, H, W] intensities in [0.05, 1] changing smoothly (a few thresholds per pixel), and times."""
    rng = np.random.default_rng(seed)
    start = rng.uniform(0.05, 1.0, (H, W))
    end = rng.uniform(0.05, 1.0, (H, W))
    wobble = rng.uniform(-0.3, 0.3, (H, W))
    s = np.linspace(0, 1, N_FRAMES)[:, None, None]
    frames = np.clip(start + (end - start) * s + wobble * np.sin(np.pi * s), 0.05, 1.0)
    return frames, np.arange(N_FRAMES, dtype=np.int64) * FRAME_DT_US


def counts_per_pixel(events) -> np.ndarray:
    return np.bincount(events.y.astype(np.int64) * W + events.x, minlength=H * W).reshape(H, W)


def test_net_events_follow_log_intensity_change():
    frames, times = smooth_clip()
    config = SimulatorConfig(contrast_threshold=0.2)
    events = simulate_events(frames, times, config)
    assert len(events) > H * W  # several events per pixel on average
    net = accumulate(events, int(times[0]), int(times[-1]) + 1)
    log_change = np.log(frames[-1] + config.log_eps) - np.log(frames[0] + config.log_eps)
    within_one = np.abs(net - log_change / config.contrast_threshold) <= 1.0
    assert within_one.mean() >= 0.95


def test_one_step_with_several_crossings_spreads_timestamps():
    sim = EventSimulator(1, 2, SimulatorConfig(contrast_threshold=0.2, log_eps=1e-3))
    sim.feed(np.array([[0.1, 0.5]]), 0)
    events = sim.feed(np.array([[0.5, 0.1]]), 10_000)
    expected = int(np.floor(np.log(0.501 / 0.101) / 0.2))  # 8 crossings each way
    assert np.sum(events.x == 0) == expected and np.sum(events.x == 1) == expected
    assert np.all(events.p[events.x == 0] == 1) and np.all(events.p[events.x == 1] == -1)
    up = events.t[events.x == 0]
    assert len(np.unique(up)) == expected and up[0] > 0 and up[-1] <= 10_000
    # Crossing times of a linear ramp in log intensity: level i*C reached at fraction i*C/total.
    total = np.log(0.501 / 0.101)
    ideal = np.round(10_000 * 0.2 * np.arange(1, expected + 1) / total)
    np.testing.assert_array_equal(up, ideal)


def test_events_sorted_and_inside_their_step():
    frames, times = smooth_clip(seed=1)
    sim = EventSimulator(H, W, SimulatorConfig())
    sim.feed(frames[0], int(times[0]))
    for frame, t_prev, t_now in zip(frames[1:], times[:-1], times[1:]):
        ev = sim.feed(frame, int(t_now))
        assert np.all(np.diff(ev.t) >= 0)
        assert np.all((ev.t >= t_prev) & (ev.t <= t_now))
        assert set(np.unique(ev.p).tolist()) <= {-1, 1}


def test_streaming_feed_equals_whole_clip():
    frames, times = smooth_clip(seed=2)
    config = SimulatorConfig(threshold_sigma=0.03, refractory_us=300, seed=5)
    whole = simulate_events(frames, times, config)
    sim = EventSimulator(H, W, config)
    parts = [sim.feed(f, int(t)) for f, t in zip(frames, times)]
    np.testing.assert_array_equal(np.concatenate([p.t for p in parts]), whole.t)
    np.testing.assert_array_equal(np.concatenate([p.x for p in parts]), whole.x)
    np.testing.assert_array_equal(np.concatenate([p.p for p in parts]), whole.p)


def test_deterministic_given_seed():
    frames, times = smooth_clip()
    config = SimulatorConfig(threshold_sigma=0.05, seed=11)
    a = simulate_events(frames, times, config)
    b = simulate_events(frames, times, config)
    for name in ("x", "y", "t", "p"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    c = simulate_events(frames, times, SimulatorConfig(threshold_sigma=0.05, seed=12))
    assert len(c) != len(a) or not np.array_equal(c.t, a.t)


def test_threshold_jitter_is_clipped_and_spread():
    sim = EventSimulator(H, W, SimulatorConfig(contrast_threshold=0.05, threshold_sigma=0.2, seed=3))
    assert sim.thresholds.min() >= MIN_CONTRAST_THRESHOLD
    assert np.any(sim.thresholds == MIN_CONTRAST_THRESHOLD)
    assert sim.thresholds.std() > 0.05
    plain = EventSimulator(H, W, SimulatorConfig(contrast_threshold=0.2))
    assert np.all(plain.thresholds == 0.2)


def test_refractory_period_reduces_counts_and_spaces_events():
    frames, times = smooth_clip()
    refractory = 800
    free = simulate_events(frames, times, SimulatorConfig())
    held = simulate_events(frames, times, SimulatorConfig(refractory_us=refractory))
    assert len(held) < len(free)
    assert np.all(counts_per_pixel(held) <= counts_per_pixel(free))
    pixel = held.y.astype(np.int64) * W + held.x
    order = np.lexsort((held.t, pixel))
    same_pixel = np.diff(pixel[order]) == 0
    gaps = np.diff(held.t[order])[same_pixel]
    assert gaps.min() >= refractory


def test_bad_frames_rejected():
    sim = EventSimulator(H, W)
    sim.feed(np.ones((H, W)), 100)
    with pytest.raises(ValueError, match="does not increase"):
        sim.feed(np.ones((H, W)), 100)
    with pytest.raises(ValueError, match="shape"):
        sim.feed(np.ones((H, W + 1)), 200)
    with pytest.raises(ValueError, match=">= 0"):
        sim.feed(-np.ones((H, W)), 200)

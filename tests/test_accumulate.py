"""accumulate / bin_events against naive loops; latent times; per-exposure binning from a source."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from edygs_ns.events.accumulate import accumulate, bin_events, exposure_bins, latent_times_us
from edygs_ns.events.exposures import Exposure
from edygs_ns.events.readers import ArrayEventSource, open_event_source
from edygs_ns.events.types import EventArray
from edygs_ns.events.writers import write_events_h5

SENSOR = (9, 13)


def random_events(n: int = 3000, span: int = 10_000, seed: int = 0) -> EventArray:
    """Random events with many equal timestamps (so boundary ties occur)."""
    rng = np.random.default_rng(seed)
    return EventArray(
        x=rng.integers(0, SENSOR[1], n).astype(np.int32),
        y=rng.integers(0, SENSOR[0], n).astype(np.int32),
        t=np.sort(rng.integers(0, span, n) // 7 * 7).astype(np.int64),
        p=(2 * rng.integers(0, 2, n) - 1).astype(np.int8),
        sensor_size=SENSOR,
    )


def naive_bins(events: EventArray, edges) -> np.ndarray:
    out = np.zeros((len(edges) - 1,) + SENSOR)
    for x, y, t, p in zip(events.x, events.y, events.t, events.p):
        for j in range(len(edges) - 1):
            if edges[j] <= t < edges[j + 1]:
                out[j, y, x] += p
    return out


def test_accumulate_matches_naive_loop():
    events = random_events()
    t0, t1 = 2_100, 7_007  # t1 is a multiple of 7: events at exactly t1 must be excluded
    expected = np.zeros(SENSOR)
    for x, y, t, p in zip(events.x, events.y, events.t, events.p):
        if t0 <= t < t1:
            expected[y, x] += p
    got = accumulate(events, t0, t1)
    assert got.dtype == np.float32 and got.shape == SENSOR
    np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("edges", [[0, 2_800, 5_600, 8_400, 9_996], [-50, 7, 14, 3_003, 20_000], [700, 701]])
def test_bin_events_matches_naive_loop(edges):
    events = random_events()
    got = bin_events(events, np.array(edges, dtype=np.int64))
    assert got.dtype == np.float32 and got.shape == (len(edges) - 1,) + SENSOR
    np.testing.assert_array_equal(got, naive_bins(events, edges))


def test_bin_events_rejects_bad_boundaries():
    events = random_events(n=10)
    with pytest.raises(ValueError, match="strictly increase"):
        bin_events(events, np.array([0, 10, 10, 20]))
    with pytest.raises(ValueError, match="at least 2"):
        bin_events(events, np.array([5]))


def test_latent_times_evenly_spaced_with_exact_ends():
    times = latent_times_us(1_000, 34_333, 5)
    assert times.dtype == np.int64
    assert times[0] == 1_000 and times[-1] == 34_333
    assert np.all(np.abs(times - np.linspace(1_000, 34_333, 5)) <= 0.5)
    assert np.all(np.diff(times) > 0)
    np.testing.assert_array_equal(latent_times_us(0, 1, 2), [0, 1])
    with pytest.raises(ValueError):
        latent_times_us(0, 3, 5)
    with pytest.raises(ValueError):
        latent_times_us(0, 100, 1)


def make_exposures(starts, duration):
    return [Exposure(i, int(s), int(s) + duration, Path(f"/x/{i:04d}.png")) for i, s in enumerate(starts)]


class RecordingSource(ArrayEventSource):
    """Records the windows requested, to check that one exposure window is read at a time."""

    def __init__(self, events: EventArray) -> None:
        super().__init__(events, name="recording")
        self.windows = []

    def window(self, t_start_us, t_end_us):
        self.windows.append((t_start_us, t_end_us))
        return super().window(t_start_us, t_end_us)


def test_exposure_bins_from_h5_source_match_full_array(tmp_path):
    events = random_events(n=4000, span=40_000)
    exposures = make_exposures([1_000, 11_000, 23_000], duration=8_000)
    k = 5
    expected = np.stack([bin_events(events, latent_times_us(e.start_us, e.end_us, k)) for e in exposures])
    path = write_events_h5(tmp_path / "ev.h5", events)
    with open_event_source(path) as source:
        got = exposure_bins(source, exposures, k)
    assert got.shape == (3, k - 1) + SENSOR and got.dtype == np.float32
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(exposure_bins(events, exposures, k), expected)
    # Each exposure's bins hold exactly its events.
    for e, bins in zip(exposures, got):
        assert bins.sum() == events.p[(events.t >= e.start_us) & (events.t < e.end_us)].sum()


def test_exposure_bins_reads_one_exposure_window_at_a_time():
    events = random_events(n=2000, span=30_000)
    exposures = make_exposures([0, 10_000, 20_000], duration=5_000)
    source = RecordingSource(events)
    exposure_bins(source, exposures, k=3)
    assert source.windows == [(e.start_us, e.end_us) for e in exposures]


def test_exposure_bins_empty_window_names_frame():
    events = random_events(n=500, span=5_000)
    exposures = make_exposures([0, 50_000], duration=1_000)
    with pytest.raises(ValueError, match=r"empty exposure window for frame 1"):
        exposure_bins(events, exposures, k=5)

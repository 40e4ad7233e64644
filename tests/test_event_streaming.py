"""Event files larger than memory: edygs-process's event stages read each exposure in bounded chunks.

The chunked route (:func:`edygs_ns.events.stream.bin_exposure` over
:meth:`EventSource.chunks`, what ``edygs-process`` runs) must give exactly what reading each
exposure's whole window into memory gave: the same EDI event maps and the same Θ estimate.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
from PIL import Image

from edygs_ns.events.accumulate import bin_chunks, bin_events, exposure_bins, exposure_window_bins, latent_times_us
from edygs_ns.events.contrast import ContrastAccumulator, estimate_contrast, next_start_us, read_span_us
from edygs_ns.events.exposures import Exposure, read_exposures
from edygs_ns.events.readers import H5EventSource, open_event_source, read_events
from edygs_ns.events.stream import bin_exposure
from edygs_ns.events.types import EventArray
from edygs_ns.events.writers import H5EventWriter, write_events_h5
from edygs_ns.scripts.synth import SynthConfig, write_synthetic_scene

#: A tiny simulated capture (seconds to write); thousands of events per exposure window.
TINY = dict(width=64, height=48, n_frames=6, supersample=1, sim_steps_per_exposure=12, novel_stride=6)
K = 3
#: A chunk far smaller than one exposure's events, so every window is read in many pieces.
SMALL_CHUNK = 97


@pytest.fixture(scope="module")
def raw(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_scene(SynthConfig(output_dir=tmp_path_factory.mktemp("raw") / "capture", **TINY))


def _linear(exposure: Exposure) -> np.ndarray:
    return np.asarray(Image.open(exposure.file).convert("RGB"), np.float32) / 255.0


def _whole_array_route(events: EventArray, exposures, k: int, scale: float):
    """The event stage as it was: each exposure's whole read span in memory, binned twice."""
    contrast = ContrastAccumulator(len(exposures))
    maps = []
    for i, exposure in enumerate(exposures):
        window = events.time_slice(*read_span_us(exposures, i))
        maps.append(bin_events(window, latent_times_us(exposure.start_us, exposure.end_us, k)) * scale)
        contrast.add(_linear(exposure), exposure, window, next_start_us(exposures, i), scale)
    return np.stack(maps), contrast.estimate()


def _chunked_route(source, exposures, k: int, scale: float, max_events: int):
    contrast = ContrastAccumulator(len(exposures))
    maps = [bin_exposure(source, exposures, i, k, scale, contrast, _linear(e), max_events) for i, e in enumerate(exposures)]
    return np.stack(maps), contrast.estimate()


def test_chunked_route_matches_whole_array_route_on_a_simulated_capture(raw: Path) -> None:
    exposures = read_exposures(raw / "exposures.csv")
    events = read_events(raw / "events.h5")
    spans = [events.time_slice(*read_span_us(exposures, i)) for i in range(len(exposures))]
    assert min(len(s) for s in spans) > 10 * SMALL_CHUNK  # every window is read in many chunks
    expected_maps, expected_theta = _whole_array_route(events, exposures, K, 1.0)
    assert expected_theta is not None
    with open_event_source(raw / "events.h5") as source:
        maps, theta = _chunked_route(source, exposures, K, 1.0, SMALL_CHUNK)
        whole_maps, whole_theta = _chunked_route(source, exposures, K, 1.0, 0)  # 0: one read per window
    np.testing.assert_array_equal(maps, expected_maps)
    np.testing.assert_array_equal(whole_maps, expected_maps)
    assert theta.to_dict() == expected_theta.to_dict() == whole_theta.to_dict()
    # the public helpers take the same chunked route
    with open_event_source(raw / "events.h5") as source:
        np.testing.assert_array_equal(exposure_bins(source, exposures, K), expected_maps)
        assert estimate_contrast([_linear(e) for e in exposures], exposures, source).to_dict() == expected_theta.to_dict()


def test_chunked_route_matches_on_a_downscaled_capture(raw: Path) -> None:
    from edygs_ns.preprocess.inputs import DownscaledEventSource

    exposures = read_exposures(raw / "exposures.csv")

    def half(exposure: Exposure) -> np.ndarray:
        frame = _linear(exposure)
        return frame.reshape(frame.shape[0] // 2, 2, frame.shape[1] // 2, 2, 3).mean(axis=(1, 3))

    with open_event_source(raw / "events.h5") as base:
        source = DownscaledEventSource(base, 2)
        contrast_a, contrast_b = ContrastAccumulator(len(exposures)), ContrastAccumulator(len(exposures))
        for i, exposure in enumerate(exposures):
            chunked = bin_exposure(source, exposures, i, K, 0.25, contrast_a, half(exposure), SMALL_CHUNK)
            window = source.window(*read_span_us(exposures, i))
            expected = bin_events(window, latent_times_us(exposure.start_us, exposure.end_us, K)) * 0.25
            contrast_b.add(half(exposure), exposure, window, next_start_us(exposures, i), 0.25)
            np.testing.assert_array_equal(chunked, expected)
    assert contrast_a.n_equations == contrast_b.n_equations
    if contrast_b.estimate() is not None:
        assert contrast_a.estimate().to_dict() == contrast_b.estimate().to_dict()


def _events(n: int, sensor=(20, 30), seed: int = 0) -> EventArray:
    rng = np.random.default_rng(seed)
    return EventArray(
        x=rng.integers(0, sensor[1], n, dtype=np.int32), y=rng.integers(0, sensor[0], n, dtype=np.int32),
        t=np.sort(rng.integers(0, 10_000, n)).astype(np.int64), p=rng.choice(np.array([-1, 1], np.int8), n),
        sensor_size=sensor,
    )


def test_a_bad_event_in_a_chunk_names_the_file_and_its_index(tmp_path: Path) -> None:
    events = _events(1000)
    x, p = events.x.copy(), events.p.copy()
    x[150] = 99  # outside the 30-pixel-wide sensor
    p[700] = 5
    path = write_events_h5(tmp_path / "bad.h5", EventArray(x, events.y, events.t, p, events.sensor_size))
    exposure = Exposure(0, 0, 10_000, Path("f.png"))
    times = latent_times_us(0, 10_000, 3)
    with open_event_source(path) as source:  # the whole-file scan (t) passes; chunks are checked as read
        with pytest.raises(ValueError) as info:
            exposure_window_bins(source, exposure, times, max_events=64)
        message = str(info.value)
        assert message.startswith(f"{path} (events 128..192): 1 of 64 events lie outside the sensor") and "\n" not in message
        assert "e.g. event 150 at x=99" in message
        x[150] = 3
    path = write_events_h5(tmp_path / "bad.h5", EventArray(x, events.y, events.t, p, events.sensor_size), overwrite=True)
    with open_event_source(path) as source:
        with pytest.raises(ValueError, match=r"bad\.h5 \(events 640\.\.704\): polarity .*offending: \[5\]; first at event index 700"):
            exposure_window_bins(source, exposure, times, max_events=64)


def test_bilinear_weighted_chunks_match_the_whole_window(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    n, (h, w) = 3000, (20, 30)
    path = tmp_path / "float.h5"
    with h5py.File(path, "w") as f:
        f["x"], f["y"] = rng.uniform(-0.5, w - 0.5, n), rng.uniform(-0.5, h - 0.5, n)
        f["t"], f["p"] = np.sort(rng.integers(0, 10_000, n)), rng.integers(0, 2, n).astype(np.int8)
        f.attrs["sensor_size"] = (h, w)
    exposure = Exposure(0, 1_000, 9_000, Path("f.png"))
    times = latent_times_us(1_000, 9_000, 5)
    with H5EventSource(path, None, None, round_coordinates=True, bilinear=True) as source:
        chunked = exposure_window_bins(source, exposure, times, max_events=101)
        whole = exposure_window_bins(source, exposure, times, max_events=0)
        np.testing.assert_array_equal(whole, bin_events(source.window(1_000, 9_000), times))
    # float64 partial sums of float32 weights, cast once: equal to float32 rounding
    np.testing.assert_allclose(chunked, whole, rtol=1e-6, atol=1e-6)


def test_bin_chunks_of_no_events_gives_zero_bins_and_counts() -> None:
    (signed, pos), counts = bin_chunks(iter(()), [(np.array([0, 5, 10]), None), (np.array([0, 10]), +1)], (4, 6))
    assert signed.shape == (2, 4, 6) and pos.shape == (1, 4, 6) and not signed.any() and not pos.any()
    assert counts == [0, 0]


def test_h5_event_writer_appends_what_write_events_h5_writes(tmp_path: Path) -> None:
    events = _events(5000)
    write_events_h5(tmp_path / "whole.h5", events)
    with H5EventWriter(tmp_path / "parts.h5", events.sensor_size) as writer:
        for i0 in range(0, len(events), 1700):
            writer.append(events.select(slice(i0, i0 + 1700)))
    assert not (tmp_path / "parts.h5.partial").exists()
    with h5py.File(tmp_path / "whole.h5") as a, h5py.File(tmp_path / "parts.h5") as b:
        for name in ("x", "y", "t", "p"):
            assert a[name].dtype == b[name].dtype and a[name].chunks == b[name].chunks
            np.testing.assert_array_equal(a[name][()], b[name][()])
        np.testing.assert_array_equal(a.attrs["sensor_size"], b.attrs["sensor_size"])
    with pytest.raises(ValueError, match=r"parts2\.h5: appended events start at t = 0 µs, before the last one"):
        with H5EventWriter(tmp_path / "parts2.h5", events.sensor_size) as writer:
            writer.append(events)
            writer.append(events)
    assert not (tmp_path / "parts2.h5").exists() and not (tmp_path / "parts2.h5.partial").exists()

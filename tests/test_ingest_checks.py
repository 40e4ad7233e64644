"""Read-time checks of real captures: units, order, NaN, corrupt files, coverage, 16-bit frames, E2NeRF files."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from edygs_ns.events.coverage import measure_coverage, resolve_coverage
from edygs_ns.events.exposures import Exposure
from edygs_ns.events.readers import _frame_from_packet, open_event_source, read_events
from edygs_ns.events.units import detect_time_unit, ticks_to_us
from edygs_ns.preprocess.frames import frames_to_rgb8, infer_bit_depth, read_frames
from edygs_ns.preprocess.e2nerf import events_file as e2nerf_events_file, read_event_bins
from edygs_ns.preprocess.inputs import InputConfig, load_capture

from capture_fixtures import EXPOSURE_US, PERIOD_US, write_tiny_capture

SENSOR = (6, 8)


def _write_h5(path: Path, t: np.ndarray, x=None, chunks=None, compression=None) -> Path:
    n = len(t)
    with h5py.File(path, "w") as f:
        f.create_dataset("x", data=np.zeros(n, np.uint16) if x is None else x, chunks=chunks, compression=compression)
        f.create_dataset("y", data=np.zeros(n, np.uint16), chunks=chunks, compression=compression)
        f.create_dataset("t", data=t, chunks=chunks, compression=compression)
        f.create_dataset("p", data=np.ones(n, np.int8), chunks=chunks, compression=compression)
        f.attrs["sensor_size"] = SENSOR
    return path


# ------------------------------------------------------------------ units


def test_ticks_to_us_per_unit() -> None:
    assert ticks_to_us(np.array([1, 2]), "s").tolist() == [1_000_000, 2_000_000]
    assert ticks_to_us(np.array([0.0015, 0.25]), "s").tolist() == [1500.0, 250000.0]
    assert ticks_to_us(np.array([3, 7]), "ms").tolist() == [3000, 7000]
    assert ticks_to_us(np.array([1999, 2000]), "ns").tolist() == [1, 2]
    assert np.isnan(ticks_to_us(np.array([np.nan]), "us")[0])


@pytest.mark.parametrize("unit,scale", [("s", 1e-6), ("ms", 1e-3), ("us", 1), ("ns", 1e3)])
def test_time_unit_detection_from_the_exposure_span(unit: str, scale: float) -> None:
    span_us = 2_500_000
    found, reason = detect_time_unit(span_us * 1.1 * scale, span_us, "us")
    assert found == unit and "closest to the 2.5 s the exposures span" in reason


def test_every_format_reads_in_the_unit_it_is_told(tmp_path: Path) -> None:
    t_s = np.array([0.5, 0.75, 1.0])
    text = tmp_path / "ev.txt"
    text.write_text("".join(f"{t} 1 1 1\n" for t in t_s))
    assert read_events(text, SENSOR).t.tolist() == [500_000, 750_000, 1_000_000]  # text: seconds by default
    ns = _write_h5(tmp_path / "ns.h5", np.array([1_000, 2_500, 9_999], np.int64))
    with open_event_source(ns, time_unit="ns") as source:
        assert source.t_range() == (1, 9)
        assert source.window(2, 10).t.tolist() == [2, 9]
    npz = tmp_path / "ms.npz"
    np.savez(npz, x=np.ones(2), y=np.ones(2), t=np.array([1, 2]), p=np.ones(2))
    assert read_events(npz, SENSOR, time_unit="ms").t.tolist() == [1000, 2000]
    with pytest.raises(ValueError, match=r"ms\.npz: unknown time unit 'min'"):
        read_events(npz, SENSOR, time_unit="min")


def test_process_detects_ns_events_and_says_so(tmp_path: Path) -> None:
    cap = write_tiny_capture(tmp_path / "raw", n=3)
    with h5py.File(cap.events, "r+") as f:
        t = f["t"][:] * 1000
        del f["t"]
        f["t"] = t
    capture = load_capture(InputConfig(exposures=cap.csv, events=cap.events), k=3, want_given_poses=False)
    capture.close()
    assert any(re.search(r"events\.h5: event timestamps read in ns \(auto-detected", n) for n in capture.notes)
    assert len(capture.frames) == 3 and not capture.dropped
    forced = load_capture(InputConfig(exposures=cap.csv, events=cap.events, events_time_unit="us"), 3, False)
    forced.close()
    assert any("read in us as given, but" in n and "ns" in n for n in forced.notes)


# ------------------------------------------------------------------ whole-file checks


def test_unsorted_timestamps_are_found_across_chunks(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from edygs_ns.events import readers

    monkeypatch.setattr(readers, "SCAN_CHUNK_EVENTS", 4)
    t = np.arange(10, dtype=np.int64)
    t[4] = 2  # the first value of the second chunk drops below the end of the first
    path = _write_h5(tmp_path / "unsorted.h5", t)
    with pytest.raises(ValueError, match=r"unsorted\.h5: timestamps are not sorted: t decreases from 3 to 2 .* event index 4"):
        open_event_source(path)


def test_nan_timestamps_and_coordinates_name_the_file_and_index(tmp_path: Path) -> None:
    t = np.arange(5, dtype=np.float64)
    t[3] = np.nan
    with pytest.raises(ValueError, match=r"nan_t\.h5: event field 't' holds NaN/inf \(first at event index 3"):
        open_event_source(_write_h5(tmp_path / "nan_t.h5", t))
    x = np.zeros(5)
    x[1] = np.inf
    with pytest.raises(ValueError, match=r"inf_x\.h5: event field 'x' holds NaN/inf \(first at event index 1"):
        open_event_source(_write_h5(tmp_path / "inf_x.h5", np.arange(5), x=x))
    text = tmp_path / "nan.txt"
    text.write_text("0.1 1 1 1\nnan 1 1 1\n")
    with pytest.raises(ValueError, match=r"nan\.txt: event field 't' holds 1 NaN/inf"):
        read_events(text, SENSOR)


def test_corrupt_hdf5_chunk_is_one_line_naming_the_file(tmp_path: Path) -> None:
    n = 4096
    path = _write_h5(tmp_path / "corrupt.h5", np.arange(n, dtype=np.int64), chunks=(512,), compression="gzip")
    with h5py.File(path, "r") as f:
        offset = f["t"].id.get_chunk_info(3).byte_offset
    data = bytearray(path.read_bytes())
    data[offset: offset + 64] = b"\xff" * 64
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError) as info:
        open_event_source(path)
    message = str(info.value)
    assert message.startswith(f"{path}: cannot read event field 't'") and "corrupt" in message and "\n" not in message


def test_pickled_npy_is_never_loaded(tmp_path: Path) -> None:
    path = tmp_path / "ev.npy"
    np.save(path, {"x": np.zeros(2)}, allow_pickle=True)
    with pytest.raises(ValueError, match=r"ev\.npy: holds pickled Python objects"):
        read_events(path, SENSOR)


# ------------------------------------------------------------------ coverage


def _exposures(n: int) -> list:
    return [Exposure(i, i * PERIOD_US, i * PERIOD_US + EXPOSURE_US, Path(f"{i}.png")) for i in range(n)]


def test_coverage_keeps_quiet_edges_reports_partial_bins_and_drops_uncovered_frames() -> None:
    exposures = _exposures(8)
    names = [str(e.file) for e in exposures]
    # events start 4 ms into frame 0 (k=3: 40 ms bins, 10% of one) and stop 30 ms before frame 7 ends
    cov = measure_coverage(4_000, 7 * PERIOD_US + 50_000, 100_000, exposures, k=3)
    assert cov.kept == list(range(7)) and cov.dropped == [7] and [p[0] for p in cov.partial] == [0]
    notes = resolve_coverage(cov, exposures, names, list(range(8)), "ev.h5")
    assert len(notes) == 2 and "dropped 1 of 8 frames" in notes[0] and "frame 7 (7.png)" in notes[0]
    assert "frame 0 (4000 µs, 10% of a bin)" in notes[1]
    # a whole bin without events (15 ms into an exposure of 20 ms bins) is never silent
    cov = measure_coverage(15_000, 8 * PERIOD_US, 100_000, exposures, k=5)
    assert cov.dropped == [0]


def test_coverage_refuses_with_the_options_that_fix_it() -> None:
    exposures = _exposures(8)
    names = [str(e.file) for e in exposures]
    cov = measure_coverage(0, 3 * PERIOD_US + EXPOSURE_US, 100_000, exposures, k=3)
    selected = list(range(2, 18, 2))  # frame_start=2, frame_stride=2 of the input's list
    with pytest.raises(ValueError, match=r"ev\.h5: .* frame 4 \(4\.png\) .*4 of 8 frames not covered\); pass "
                                         r"--frame-start 2 --frame-end 9 "):
        resolve_coverage(cov, exposures, names, selected, "ev.h5")
    cov = measure_coverage(10 * PERIOD_US, 11 * PERIOD_US, 1000, exposures, k=3)
    with pytest.raises(ValueError, match="no frame is covered; check"):
        resolve_coverage(cov, exposures, names, list(range(8)), "ev.h5")


def test_first_frame_before_the_events_is_dropped_without_options(tmp_path: Path) -> None:
    """The DAVIS case: frame 0's exposure starts 30 ms before the first event."""
    cap = write_tiny_capture(tmp_path / "raw", n=5, event_span_us=(30_000, 4 * PERIOD_US + EXPOSURE_US))
    capture = load_capture(InputConfig(exposures=cap.csv, events=cap.events), k=3, want_given_poses=False)
    capture.close()
    assert capture.dropped == [0] and capture.selected == [1, 2, 3, 4] and len(capture.frames) == 4
    assert [e.frame for e in capture.exposures] == [1, 2, 3, 4]
    assert any("dropped 1 of 5 frames" in n and "0000.png" in n for n in capture.notes)


# ------------------------------------------------------------------ frames


def test_twelve_bit_png_is_not_darkened_and_the_depth_is_said(tmp_path: Path) -> None:
    codes = np.array([[0, 1024], [2048, 4095]], np.uint16)
    paths = []
    for i, scale in enumerate((1, 2)):
        paths.append(tmp_path / f"{i}.png")
        cv2.imwrite(str(paths[-1]), codes // scale)
    frames, note = read_frames(paths)
    assert frames[0][1, 1].tolist() == [255] * 3 and frames[1][1, 1, 0] == 127  # one depth for the capture
    assert "codes up to 4095: read as 12-bit" in note and "--frame-bits" in note
    full, _ = read_frames(paths, bits=16)
    assert full[0][1, 1, 0] == 16
    with pytest.raises(ValueError, match="codes up to 4095, more than 10-bit"):
        read_frames(paths, bits=10)
    assert infer_bit_depth([np.zeros((2, 2), np.uint8)]) == (None, "")


def test_aedat_gray16_frames_are_read_and_scaled() -> None:
    """aedat >= 2.3 gives DAVIS APS frames as I;16 with 10-bit codes."""
    packet = {"format": "I;16", "pixels": np.array([[1, 2], [3, 1023]], np.uint16), "exposure_begin_t": 10,
              "exposure_end_t": 20}
    aps = _frame_from_packet(packet, Path("rec.aedat4"))
    assert aps.image.dtype == np.uint16 and aps.image.shape == (2, 2)
    frames, note = frames_to_rgb8([aps.image], ["rec.aedat4 frame 0"])
    assert frames[0][1, 1].tolist() == [255, 255, 255] and "10-bit" in note


def test_truncated_png_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "cut.png"
    cv2.imwrite(str(path), np.full((8, 8, 3), 100, np.uint8))
    path.write_bytes(path.read_bytes()[:40])
    with pytest.raises(ValueError, match=r"cut\.png: cannot decode the image"):
        read_frames([path])


# ------------------------------------------------------------------ E2NeRF files


def test_e2nerf_event_pt_name_and_four_d_bins(tmp_path: Path) -> None:
    import torch

    with pytest.raises(FileNotFoundError, match="events.pt and event.pt"):
        e2nerf_events_file(tmp_path)
    grid = torch.arange(2 * 4 * 3 * 5, dtype=torch.float32).reshape(2, 4, 3, 5)
    torch.save(grid, tmp_path / "event.pt")
    path = e2nerf_events_file(tmp_path)
    assert path.name == "event.pt"
    four_d = read_event_bins(path, 2, 3, 5, bins=4)
    torch.save(grid.reshape(2, 4, 15), tmp_path / "flat.pt")
    np.testing.assert_array_equal(four_d, read_event_bins(tmp_path / "flat.pt", 2, 3, 5, bins=4))
    with pytest.raises(ValueError, match=r"event\.pt: event bins have shape \(2, 4, 3, 5\), expected \(2, 4, 12\) or \(2, 4, 3, 4\)"):
        read_event_bins(path, 2, 3, 4, bins=4)
    torch.save({"not": "a tensor"}, tmp_path / "dict.pt")
    with pytest.raises(ValueError, match=r"dict\.pt: expected one tensor"):
        read_event_bins(tmp_path / "dict.pt", 2, 3, 5, bins=4)

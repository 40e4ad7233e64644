"""Readers of every event format, on small files written here, and windowed EventSource reads."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from edygs_ns.events import readers
from edygs_ns.events.readers import ApsFrame, open_event_source, read_aedat4, read_events
from edygs_ns.events.types import EventArray
from edygs_ns.events.writers import write_events_h5, write_events_npz, write_events_txt

SENSOR = (24, 32)
NUM_EVENTS = 400
T_SPAN_US = 50_000
T_START_US = 1_000


def make_events(
    n: int = NUM_EVENTS, sensor=SENSOR, seed: int = 0, t_start: int = T_START_US, span: int = T_SPAN_US
) -> EventArray:
    rng = np.random.default_rng(seed)
    return EventArray(
        x=rng.integers(0, sensor[1], n).astype(np.int32),
        y=rng.integers(0, sensor[0], n).astype(np.int32),
        t=np.sort(rng.integers(t_start, t_start + span, n)).astype(np.int64),
        p=(2 * rng.integers(0, 2, n) - 1).astype(np.int8),
        sensor_size=sensor,
    )


def assert_same_events(a: EventArray, b: EventArray) -> None:
    assert a.sensor_size == b.sensor_size
    for name in ("x", "y", "t", "p"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.x.dtype == np.int32 and a.y.dtype == np.int32 and a.t.dtype == np.int64 and a.p.dtype == np.int8


def write_dsec(path: Path, events: EventArray, t_offset: int, as_attribute: bool) -> None:
    """A DSEC-style file: events/ group with uint32 t relative to a root t_offset, p in {0, 1}."""
    with h5py.File(path, "w") as f:
        group = f.create_group("events")
        group["x"] = events.x.astype(np.uint16)
        group["y"] = events.y.astype(np.uint16)
        group["t"] = (events.t - t_offset).astype(np.uint32)
        group["p"] = (events.p > 0).astype(np.uint8)
        if as_attribute:
            f.attrs["t_offset"] = t_offset
        else:
            f["t_offset"] = np.int64(t_offset)


def write_structured_npy(path: Path, events: EventArray) -> None:
    table = np.zeros(len(events), dtype=[("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])
    for name in ("x", "y", "t", "p"):
        table[name] = getattr(events, name)
    np.save(path, table)


# ---------------------------------------------------------------- HDF5


def test_h5_root_round_trip_reads_sensor_size_from_file(tmp_path):
    events = make_events()
    path = write_events_h5(tmp_path / "ev.h5", events)
    with h5py.File(path, "r") as f:
        assert tuple(f.attrs["sensor_size"]) == SENSOR
        assert f["t"].dtype == np.int64 and f["p"].dtype == np.int8
        assert f["t"].chunks is not None and f["t"].compression == "gzip"
    assert_same_events(read_events(path), events)


def test_h5_writer_refuses_to_overwrite(tmp_path):
    events = make_events()
    path = write_events_h5(tmp_path / "ev.h5", events)
    with pytest.raises(FileExistsError, match="ev.h5"):
        write_events_h5(path, make_events(seed=1))
    write_events_h5(path, make_events(seed=1), overwrite=True)
    assert_same_events(read_events(path), make_events(seed=1))


@pytest.mark.parametrize("as_attribute", [False, True])
def test_h5_dsec_group_adds_t_offset(tmp_path, as_attribute):
    offset = 7_000_000_000
    events = make_events(t_start=offset + 500)
    path = tmp_path / "dsec.h5"
    write_dsec(path, events, offset, as_attribute)
    got = read_events(path, sensor_size=SENSOR)
    assert_same_events(got, events)
    # An explicit offset replaces the file's.
    relative = read_events(path, sensor_size=SENSOR, t_offset_us=0)
    np.testing.assert_array_equal(relative.t, events.t - offset)


def test_h5_without_sensor_size_asks_for_it(tmp_path):
    path = tmp_path / "dsec.h5"
    write_dsec(path, make_events(), 0, as_attribute=False)
    with pytest.raises(ValueError, match=r"dsec\.h5.*sensor_size"):
        read_events(path)


def test_h5_sensor_size_argument_must_agree_with_file(tmp_path):
    path = write_events_h5(tmp_path / "ev.h5", make_events())
    with pytest.raises(ValueError, match=r"ev\.h5.*\(24, 32\)"):
        read_events(path, sensor_size=(10, 10))


def test_h5_without_event_datasets(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["images"] = np.zeros((2, 3))
    with pytest.raises(ValueError, match=r"other\.h5.*no event datasets"):
        read_events(path, sensor_size=SENSOR)


# ---------------------------------------------------------------- NumPy


def test_npz_round_trip(tmp_path):
    events = make_events()
    path = write_events_npz(tmp_path / "ev.npz", events)
    assert_same_events(read_events(path), events)


def test_npz_with_t_offset_argument(tmp_path):
    events = make_events()
    path = write_events_npz(tmp_path / "ev.npz", events)
    np.testing.assert_array_equal(read_events(path, t_offset_us=250).t, events.t + 250)


def test_npz_missing_field_names_file(tmp_path):
    path = tmp_path / "bad.npz"
    np.savez(path, x=np.zeros(3), y=np.zeros(3), t=np.arange(3))
    with pytest.raises(ValueError, match=r"bad\.npz.*'p'"):
        read_events(path, sensor_size=SENSOR)


def test_npy_structured_array_needs_sensor_size(tmp_path):
    events = make_events()
    path = tmp_path / "ev.npy"
    write_structured_npy(path, events)
    assert_same_events(read_events(path, sensor_size=SENSOR), events)
    with pytest.raises(ValueError, match=r"ev\.npy.*sensor_size"):
        read_events(path)


def test_pickled_npy_is_refused_never_unpickled(tmp_path):
    events = make_events()
    path = tmp_path / "ev.npy"
    np.save(path, {"x": events.x, "y": events.y, "t": events.t, "p": (events.p > 0).astype(np.uint8)})
    for read in (read_events, open_event_source):
        with pytest.raises(ValueError, match=r"ev\.npy: holds pickled Python objects.*\.npz"):
            read(path, sensor_size=SENSOR)
    sources = [p for p in Path(__file__).resolve().parents[1].joinpath("edygs_ns").rglob("*.py")]
    assert not [p for p in sources if "allow_pickle=True" in p.read_text()]


# ---------------------------------------------------------------- text


def test_txt_round_trip_through_writer(tmp_path):
    events = make_events()
    path = write_events_txt(tmp_path / "ev.txt", events)
    lines = path.read_text().splitlines()
    assert lines[0].startswith("#")
    first_event = [ln for ln in lines if not ln.startswith("#")][0].split()
    assert float(first_event[0]) == pytest.approx(events.t[0] / 1e6)
    assert first_event[3] in ("0", "1")
    assert_same_events(read_events(path), events)


def test_txt_v2e_style_header_seconds_and_01_polarity(tmp_path):
    path = tmp_path / "v2e-dvs-events.txt"
    path.write_text(
        "# Format is time (float s), x, y, polarity (0=off, 1=on)\n"
        "# created by a simulator\n"
        "0.000010 3 4 1\n"
        "0.000250 5 6 0\n"
        "1.500000 31 23 1\n"
    )
    got = read_events(path, sensor_size=SENSOR)
    np.testing.assert_array_equal(got.t, [10, 250, 1_500_000])
    np.testing.assert_array_equal(got.x, [3, 5, 31])
    np.testing.assert_array_equal(got.y, [4, 6, 23])
    np.testing.assert_array_equal(got.p, [1, -1, 1])
    with pytest.raises(ValueError, match=r"v2e-dvs-events\.txt.*sensor_size"):
        read_events(path)


def test_txt_eth_width_height_first_line(tmp_path):
    path = tmp_path / "events.txt"
    path.write_text("32 24\n0.1 1 2 0\n0.2 31 23 1\n")
    got = read_events(path)
    assert got.sensor_size == (24, 32)
    np.testing.assert_array_equal(got.t, [100_000, 200_000])


def test_csv_comma_separated(tmp_path):
    path = tmp_path / "events.csv"
    path.write_text("# t,x,y,p\n0.5,1,2,1\n0.75,3,4,0\n")
    got = read_events(path, sensor_size=SENSOR)
    np.testing.assert_array_equal(got.t, [500_000, 750_000])
    np.testing.assert_array_equal(got.p, [1, -1])


def test_txt_malformed_line_names_file(tmp_path):
    path = tmp_path / "broken.txt"
    path.write_text("0.1 1 2 1\n0.2 oops 2 1\n")
    with pytest.raises(ValueError, match=r"broken\.txt"):
        read_events(path, sensor_size=SENSOR)


# ---------------------------------------------------------------- AEDAT4


def write_aedat4(path: Path, events: EventArray, frames) -> None:
    dv = pytest.importorskip("dv_processing")
    height, width = events.sensor_size
    config = dv.io.MonoCameraWriter.Config("test-davis")
    config.addEventStream((width, height))
    config.addFrameStream((width, height))
    writer = dv.io.MonoCameraWriter(str(path), config)
    store = dv.EventStore()
    for x, y, t, p in zip(events.x, events.y, events.t, events.p):
        store.push_back(int(t), int(x), int(y), bool(p > 0))
    writer.writeEvents(store)
    for image, start, exposure in frames:
        # dv-processing takes OpenCV (BGR) colour images.
        pixels = image[..., ::-1].copy() if image.ndim == 3 else image
        writer.writeFrame(dv.Frame(int(start), int(exposure), 0, 0, pixels, dv.FrameSource.SENSOR))
    del writer  # the file is finalised when the writer is destroyed


def test_aedat4_round_trip_events_and_exposures(tmp_path):
    events = make_events(n=120)
    rng = np.random.default_rng(3)
    grey = rng.integers(0, 256, SENSOR, dtype=np.uint8)
    colour = rng.integers(0, 256, SENSOR + (3,), dtype=np.uint8)
    frames = [(grey, 2_000, 9_000), (colour, 20_000, 4_500)]
    path = tmp_path / "rec.aedat4"
    write_aedat4(path, events, frames)

    got, aps = read_aedat4(path)
    assert_same_events(got, events)
    assert len(aps) == 2 and all(isinstance(f, ApsFrame) for f in aps)
    for frame, (image, start, exposure) in zip(aps, frames):
        assert frame.exposure_start_us == start
        assert frame.exposure_end_us == start + exposure
        assert frame.image.dtype == np.uint8
        np.testing.assert_array_equal(frame.image, image)
    assert_same_events(read_events(path), events)


def test_aedat4_garbage_names_file(tmp_path):
    path = tmp_path / "junk.aedat4"
    path.write_bytes(b"not an aedat file at all")
    with pytest.raises(ValueError, match=r"junk\.aedat4"):
        read_aedat4(path)


# ---------------------------------------------------------------- dispatch


def test_unknown_suffix_and_missing_file(tmp_path):
    path = tmp_path / "events.bin"
    path.write_bytes(b"\x00")
    with pytest.raises(ValueError, match=r"events\.bin.*unknown event file type"):
        read_events(path)
    with pytest.raises(FileNotFoundError, match=r"nope\.h5"):
        read_events(tmp_path / "nope.h5")


# ---------------------------------------------------------------- windowed sources


def _write_any(kind: str, tmp_path: Path, events: EventArray):
    """Write ``events`` in format ``kind``; return (path, kwargs for open_event_source)."""
    if kind == "h5":
        return write_events_h5(tmp_path / "w.h5", events), {}
    if kind == "dsec":
        offset = int(events.t[0]) - 17
        write_dsec(tmp_path / "w_dsec.h5", events, offset, as_attribute=False)
        return tmp_path / "w_dsec.h5", {"sensor_size": events.sensor_size}
    if kind == "npy":
        write_structured_npy(tmp_path / "w.npy", events)
        return tmp_path / "w.npy", {"sensor_size": events.sensor_size}
    if kind == "npz":
        return write_events_npz(tmp_path / "w.npz", events), {}
    return write_events_txt(tmp_path / "w.txt", events), {}


@pytest.mark.parametrize("kind", ["h5", "dsec", "npy", "npz", "txt"])
def test_window_equals_slice_of_full_array(tmp_path, monkeypatch, kind):
    # Tiny search blocks so that the binary search really probes single elements.
    monkeypatch.setattr(readers, "SEARCH_BLOCK_EVENTS", 5)
    # Few distinct timestamps, so windows often start on runs of equal t.
    events = make_events(n=1500, span=300)
    path, kwargs = _write_any(kind, tmp_path, events)
    full = read_events(path, **kwargs)
    rng = np.random.default_rng(4)
    t0, t1 = int(events.t[0]), int(events.t[-1])
    starts = rng.integers(t0 - 10, t1 + 10, 10).tolist() + events.t[::97].tolist() + [t0 - 5, t1, t1 + 1]
    with open_event_source(path, **kwargs) as source:
        assert source.sensor_size == SENSOR
        assert source.t_range() == (t0, t1)
        assert len(source) == len(events)
        for start in starts:
            for length in (1, 7, 120, 1_000):
                expected = events.time_slice(start, start + length)
                got = source.window(start, start + length)
                assert_same_events(got, expected)
        assert_same_events(source.window(t0, t1 + 1), full)


def test_h5_window_reads_only_the_window(tmp_path, monkeypatch):
    """The windowed HDF5 source must not read the whole t dataset for a small window."""
    monkeypatch.setattr(readers, "SEARCH_BLOCK_EVENTS", 64)
    events = make_events(n=20_000)
    path = write_events_h5(tmp_path / "big.h5", events)
    read_sizes = []
    with open_event_source(path) as source:
        t_column = source._columns["t"]

        class CountingColumn:
            shape = t_column.shape

            def __getitem__(self, key):
                out = np.asarray(t_column[key])
                read_sizes.append(out.size)
                return out

        source._columns["t"] = CountingColumn()
        start = int(events.t[10_000])
        got = source.window(start, start + 50)
    assert_same_events(got, events.time_slice(start, start + 50))
    assert sum(read_sizes) < len(events) // 20

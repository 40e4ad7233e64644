"""validate_events: conversion of good columns, and one test per kind of bad input."""

from __future__ import annotations

import re

import h5py
import numpy as np
import pytest

from edygs_ns.events.readers import read_events
from edygs_ns.events.validate import validate_events

SENSOR = (10, 20)
SOURCE = "/data/capture/events.h5"


def good_columns(n: int = 8):
    rng = np.random.default_rng(0)
    return {
        "x": rng.integers(0, SENSOR[1], n),
        "y": rng.integers(0, SENSOR[0], n),
        "t": np.arange(n, dtype=np.int64) * 10,
        "p": rng.integers(0, 2, n),
    }


def validate(cols, sensor=SENSOR, source=SOURCE):
    return validate_events(cols["x"], cols["y"], cols["t"], cols["p"], sensor, source)


def test_polarity_01_becomes_signed_and_dtypes_are_canonical():
    cols = good_columns()
    ev = validate(cols)
    np.testing.assert_array_equal(ev.p, np.where(cols["p"] == 1, 1, -1))
    np.testing.assert_array_equal(ev.x, cols["x"])
    assert (ev.x.dtype, ev.y.dtype, ev.t.dtype, ev.p.dtype) == (np.int32, np.int32, np.int64, np.int8)
    assert ev.sensor_size == SENSOR


def test_signed_and_boolean_polarity_accepted():
    cols = good_columns()
    signed = dict(cols, p=2 * cols["p"] - 1)
    boolean = dict(cols, p=cols["p"].astype(bool))
    np.testing.assert_array_equal(validate(signed).p, validate(cols).p)
    np.testing.assert_array_equal(validate(boolean).p, validate(cols).p)


def test_float_timestamps_are_rounded_to_microseconds():
    cols = dict(good_columns(), t=np.array([0.4, 10.6, 20.0, 30.2, 40.0, 50.0, 60.0, 70.0]))
    np.testing.assert_array_equal(validate(cols).t, [0, 11, 20, 30, 40, 50, 60, 70])


def test_coordinates_outside_sensor():
    cols = good_columns()
    cols["x"][3] = SENSOR[1]  # one past the last column
    cols["y"][5] = -1
    with pytest.raises(ValueError) as err:
        validate(cols)
    msg = str(err.value)
    assert SOURCE in msg
    assert "2 of 8 events lie outside the sensor" in msg
    assert f"event 3 at x={SENSOR[1]}" in msg


def test_nan_timestamp():
    cols = dict(good_columns(), t=np.arange(8, dtype=np.float64))
    cols["t"][2] = np.nan
    with pytest.raises(ValueError, match=re.escape(SOURCE) + r".*'t'.*1 NaN/inf"):
        validate(cols)


def test_inf_coordinate():
    cols = dict(good_columns(), x=np.ones(8))
    cols["x"][6] = np.inf
    with pytest.raises(ValueError, match=re.escape(SOURCE) + r".*'x'.*NaN/inf.*index 6"):
        validate(cols)


def test_non_monotonic_timestamps_count_decreases():
    cols = good_columns()
    cols["t"] = np.array([0, 5, 3, 8, 9, 2, 10, 11])
    with pytest.raises(ValueError, match=re.escape(SOURCE) + r".*not monotonic.*decreases 2 time"):
        validate(cols)


def test_polarity_outside_allowed_values():
    cols = dict(good_columns(), p=np.array([0, 1, 2, 1, 0, 1, 0, 1]))
    with pytest.raises(ValueError, match=re.escape(SOURCE) + r".*polarity.*offending: \[2\]"):
        validate(cols)


def test_polarity_mixing_conventions():
    cols = dict(good_columns(), p=np.array([-1, 0, 1, 1, 0, 1, -1, 1]))
    with pytest.raises(ValueError, match=re.escape(SOURCE) + r".*polarity"):
        validate(cols)


def test_mismatched_lengths():
    cols = good_columns()
    cols["p"] = cols["p"][:-1]
    with pytest.raises(ValueError, match=re.escape(SOURCE) + r".*mismatched lengths"):
        validate(cols)


def test_fractional_coordinates():
    cols = dict(good_columns(), y=np.full(8, 2.5))
    with pytest.raises(ValueError, match=re.escape(SOURCE) + r".*'y'.*non-integer"):
        validate(cols)


def test_bad_sensor_size():
    with pytest.raises(ValueError, match=re.escape(SOURCE) + r".*sensor_size"):
        validate(good_columns(), sensor=(0, 20))


# The readers route every file through validate_events: the message names the file.


def test_reader_error_names_file_for_out_of_sensor_events(tmp_path):
    path = tmp_path / "wide.txt"
    path.write_text("0.1 1 1 1\n0.2 25 1 0\n")
    with pytest.raises(ValueError, match=re.escape(str(path)) + r".*1 of 2 events lie outside"):
        read_events(path, sensor_size=SENSOR)


def test_reader_error_names_file_for_unsorted_h5(tmp_path):
    path = tmp_path / "unsorted.h5"
    with h5py.File(path, "w") as f:
        f["x"], f["y"] = np.zeros(4, np.uint16), np.zeros(4, np.uint16)
        f["t"], f["p"] = np.array([5, 4, 6, 7]), np.ones(4, np.int8)
        f.attrs["sensor_size"] = SENSOR
    with pytest.raises(ValueError, match=re.escape(str(path)) + r": timestamps are not sorted: t decreases from 5 to 4 .* event index 1"):
        read_events(path)


def test_reader_error_names_file_for_nan_in_npz(tmp_path):
    path = tmp_path / "nan.npz"
    np.savez(path, x=np.array([1.0, np.nan]), y=np.zeros(2), t=np.arange(2), p=np.ones(2))
    with pytest.raises(ValueError, match=re.escape(str(path)) + r".*NaN"):
        read_events(path, sensor_size=SENSOR)

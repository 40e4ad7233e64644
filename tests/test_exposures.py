"""The exposure table: round trip, and one test per kind of bad table."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from edygs_ns.events.exposures import Exposure, check_frames_match, read_exposures, write_exposures

HEADER = "frame,exposure_start_us,exposure_end_us,file\n"


def make_capture(tmp_path: Path, n: int = 3) -> Path:
    """A capture folder with n frame files; returns the CSV path (not yet written)."""
    frames = tmp_path / "raw" / "frames"
    frames.mkdir(parents=True)
    for i in range(n):
        (frames / f"{i:04d}.png").write_bytes(b"png")
    return tmp_path / "raw" / "exposures.csv"


def write_rows(csv_path: Path, rows, header: str = HEADER) -> None:
    csv_path.write_text(header + "".join(r + "\n" for r in rows))


def test_round_trip_resolves_files_against_the_csv_folder(tmp_path):
    csv_path = make_capture(tmp_path)
    folder = csv_path.parent.resolve()
    exposures = [Exposure(i, 1000 * i, 1000 * i + 600, folder / "frames" / f"{i:04d}.png") for i in range(3)]
    write_exposures(csv_path, exposures, relative_to=csv_path.parent)
    assert "frames/0001.png" in csv_path.read_text()
    assert csv_path.read_text().startswith(HEADER)
    got = read_exposures(csv_path)
    assert got == exposures
    assert all(e.file.is_absolute() for e in got)


def test_write_relative_to_another_folder(tmp_path):
    csv_path = make_capture(tmp_path, n=1)
    image = (csv_path.parent / "frames" / "0000.png").resolve()
    out = tmp_path / "scene" / "exposures.csv"
    write_exposures(out, [Exposure(0, 0, 10, image)], relative_to=out.parent)
    assert "../raw/frames/0000.png" in out.read_text()
    assert read_exposures(out)[0].file == image


def test_wrong_header(tmp_path):
    csv_path = make_capture(tmp_path)
    write_rows(csv_path, ["0,0,10,frames/0000.png"], header="frame,start,end,file\n")
    with pytest.raises(ValueError, match=re.escape(str(csv_path)) + r", line 1: header must be exactly"):
        read_exposures(csv_path)


def test_non_integer_time(tmp_path):
    csv_path = make_capture(tmp_path)
    write_rows(csv_path, ["0,0,10,frames/0000.png", "1,20.5,30,frames/0001.png"])
    with pytest.raises(ValueError, match=re.escape(str(csv_path)) + r", line 3: exposure_start_us '20.5' is not an integer"):
        read_exposures(csv_path)


def test_end_not_after_start(tmp_path):
    csv_path = make_capture(tmp_path)
    write_rows(csv_path, ["0,0,10,frames/0000.png", "1,30,30,frames/0001.png"])
    with pytest.raises(ValueError, match=re.escape(str(csv_path)) + r", line 3: exposure_end_us 30 must be greater"):
        read_exposures(csv_path)


def test_frames_not_increasing(tmp_path):
    csv_path = make_capture(tmp_path)
    write_rows(csv_path, ["0,0,10,frames/0000.png", "2,20,30,frames/0001.png", "2,40,50,frames/0002.png"])
    with pytest.raises(ValueError, match=re.escape(str(csv_path)) + r", line 4: frame 2 does not increase"):
        read_exposures(csv_path)


def test_missing_image_file(tmp_path):
    csv_path = make_capture(tmp_path)
    write_rows(csv_path, ["0,0,10,frames/0000.png", "1,20,30,frames/9999.png"])
    with pytest.raises(FileNotFoundError, match=re.escape(str(csv_path)) + r", line 3: image file 'frames/9999.png'"):
        read_exposures(csv_path)


def test_wrong_number_of_fields(tmp_path):
    csv_path = make_capture(tmp_path)
    write_rows(csv_path, ["0,0,10"])
    with pytest.raises(ValueError, match=re.escape(str(csv_path)) + r", line 2: expected 4 fields"):
        read_exposures(csv_path)


def test_missing_csv(tmp_path):
    with pytest.raises(FileNotFoundError, match="exposures.csv"):
        read_exposures(tmp_path / "exposures.csv")


def test_check_frames_match(tmp_path):
    csv_path = make_capture(tmp_path)
    write_rows(csv_path, [f"{i},{100 * i},{100 * i + 50},frames/{i:04d}.png" for i in range(3)])
    exposures = read_exposures(csv_path)
    frame_files = sorted((csv_path.parent / "frames").glob("*.png"))
    check_frames_match(exposures, frame_files, str(csv_path))
    with pytest.raises(ValueError, match=re.escape(str(csv_path)) + r".*2 frame image\(s\) but 3 exposure"):
        check_frames_match(exposures, frame_files[:2], str(csv_path))


def test_overlapping_exposures_name_the_line(tmp_path):
    csv_path = make_capture(tmp_path)
    write_rows(csv_path, ["0,0,100,frames/0000.png", "1,90,150,frames/0001.png"])
    with pytest.raises(ValueError, match=re.escape(str(csv_path)) + r", line 3: exposure of frame 1 \[90, 150\] µs "
                                                                    r"overlaps the previous exposure \(frame 0: \[0, 100\]"):
        read_exposures(csv_path)


def test_backwards_exposures_name_the_line(tmp_path):
    csv_path = make_capture(tmp_path)
    write_rows(csv_path, ["0,1000,1100,frames/0000.png", "1,1200,1300,frames/0001.png", "2,500,600,frames/0002.png"])
    with pytest.raises(ValueError, match=re.escape(str(csv_path)) + r", line 4: exposure of frame 2 .* goes backwards"):
        read_exposures(csv_path)
    write_rows(csv_path, ["0,0,100,frames/0000.png", "1,100,200,frames/0001.png"])  # back to back is fine
    assert len(read_exposures(csv_path)) == 2


def test_exposure_sequence_of_a_recording(tmp_path):
    from edygs_ns.events.exposures import check_exposure_sequence

    rows = [Exposure(0, 0, 100, tmp_path), Exposure(1, 50, 150, tmp_path)]
    with pytest.raises(ValueError, match=r"rec\.aedat4: exposure of frame 1 \[50, 150\] µs overlaps"):
        check_exposure_sequence(rows, "rec.aedat4")
    check_exposure_sequence(rows[:1], "rec.aedat4")

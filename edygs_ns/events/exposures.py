"""The exposure table: when each blurry frame's shutter was open, and which image it is.

CSV format (docs/layouts.md), header exactly ``frame,exposure_start_us,exposure_end_us,file``;
one row per blurry frame, frames strictly increasing, times in µs on the event clock, ``file``
relative to the CSV's folder. A camera exposes one frame at a time: each exposure starts after
the previous one ended (times never go backwards, exposures never overlap).
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass
from pathlib import Path
from typing import List, Sequence, Union

PathLike = Union[str, Path]

#: The exact header of an exposure table.
EXPOSURE_HEADER = ("frame", "exposure_start_us", "exposure_end_us", "file")


@dataclass(frozen=True)
class Exposure:
    """One blurry frame's exposure.

    Attributes:
        frame: index of the blurry frame (strictly increasing along the table).
        start_us: shutter opens, µs on the event clock.
        end_us: shutter closes, µs on the event clock (> start_us).
        file: absolute path of the blurry image.
    """

    frame: int
    start_us: int
    end_us: int
    file: Path


def _parse_int(text: str, column: str, where: str) -> int:
    try:
        return int(text.strip())
    except ValueError:
        raise ValueError(f"{where}: {column} {text!r} is not an integer") from None


def read_exposures(csv_path: PathLike) -> List[Exposure]:
    """Read and check an exposure table.

    Args:
        csv_path: the CSV file; ``file`` entries are resolved against its folder.

    Returns:
        One Exposure per row, with absolute image paths.

    Raises:
        FileNotFoundError: the CSV, or an image it lists, does not exist (names CSV and line).
        ValueError: wrong header, wrong number of fields, non-integer times or frame, end <= start,
            frames not strictly increasing, or an exposure that starts before the previous one
            ended (backwards or overlapping); the message names the CSV and the line.
    """
    csv_path = Path(csv_path)
    if not csv_path.is_file():
        raise FileNotFoundError(f"{csv_path}: exposure table not found")
    folder = csv_path.resolve().parent
    exposures: List[Exposure] = []
    with open(csv_path, newline="", encoding="utf-8") as f:
        rows = csv.reader(f)
        header = next(rows, None)
        if header is None or tuple(h.strip() for h in header) != EXPOSURE_HEADER:
            raise ValueError(f"{csv_path}, line 1: header must be exactly {','.join(EXPOSURE_HEADER)!r}, got {header!r}")
        for row in rows:
            line = rows.line_num
            where = f"{csv_path}, line {line}"
            if not row or all(not cell.strip() for cell in row):
                continue
            if len(row) != len(EXPOSURE_HEADER):
                raise ValueError(f"{where}: expected {len(EXPOSURE_HEADER)} fields, got {len(row)}: {row!r}")
            frame = _parse_int(row[0], "frame", where)
            start = _parse_int(row[1], "exposure_start_us", where)
            end = _parse_int(row[2], "exposure_end_us", where)
            if end <= start:
                raise ValueError(f"{where}: exposure_end_us {end} must be greater than exposure_start_us {start}")
            if exposures and frame <= exposures[-1].frame:
                raise ValueError(f"{where}: frame {frame} does not increase (previous row: frame {exposures[-1].frame})")
            if exposures and start < exposures[-1].end_us:
                previous = exposures[-1]
                fault = "goes backwards" if start < previous.start_us else "overlaps the previous exposure"
                raise ValueError(
                    f"{where}: exposure of frame {frame} [{start}, {end}] µs {fault} (frame {previous.frame}: "
                    f"[{previous.start_us}, {previous.end_us}] µs); exposures must follow one another in time"
                )
            image = (folder / row[3].strip()).resolve()
            if not image.is_file():
                raise FileNotFoundError(f"{where}: image file {row[3].strip()!r} not found (looked for {image})")
            exposures.append(Exposure(frame=frame, start_us=start, end_us=end, file=image))
    return exposures


def write_exposures(csv_path: PathLike, exposures: Sequence[Exposure], relative_to: PathLike) -> Path:
    """Write an exposure table, image paths written relative to ``relative_to``.

    Args:
        csv_path: destination CSV.
        exposures: the rows to write.
        relative_to: folder the ``file`` column is relative to (normally the CSV's folder, so
            that :func:`read_exposures` finds the images again).

    Returns:
        The path written.
    """
    csv_path = Path(csv_path)
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    base = Path(relative_to).resolve()
    with open(csv_path, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(EXPOSURE_HEADER)
        for e in exposures:
            rel = Path(os.path.relpath(Path(e.file).resolve(), base)).as_posix()
            writer.writerow([int(e.frame), int(e.start_us), int(e.end_us), rel])
    return csv_path


def check_frames_match(exposures: Sequence[Exposure], frame_files: Sequence[PathLike], source: str) -> None:
    """Check that there is exactly one exposure per frame image.

    Args:
        exposures: the exposure table's rows.
        frame_files: the blurry frame images found.
        source: what to name in the error (the CSV or the capture folder).

    Raises:
        ValueError: the counts differ.
    """
    if len(exposures) != len(frame_files):
        raise ValueError(
            f"{source}: {len(frame_files)} frame image(s) but {len(exposures)} exposure(s); "
            "every blurry frame needs exactly one exposure row"
        )


def check_exposure_sequence(exposures: Sequence[Exposure], source: str) -> None:
    """Check that exposures follow one another: each starts after the previous one ended.

    Args:
        exposures: in the order the input lists them.
        source: what to name in the error (e.g. the recording).

    Raises:
        ValueError: an exposure goes backwards or overlaps the previous one (names both frames).
    """
    for previous, exposure in zip(exposures, exposures[1:]):
        if exposure.start_us < previous.end_us:
            fault = "goes backwards" if exposure.start_us < previous.start_us else "overlaps the previous exposure"
            raise ValueError(
                f"{source}: exposure of frame {exposure.frame} [{exposure.start_us}, {exposure.end_us}] µs {fault} "
                f"(frame {previous.frame}: [{previous.start_us}, {previous.end_us}] µs); exposures must follow one another in time"
            )

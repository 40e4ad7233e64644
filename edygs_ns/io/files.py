"""Small readers shared by every scene format: JSON objects, required keys and files, poses stored
as nested lists, numbered files. Each error is one line naming the file and the fault."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any, Dict, List, Sequence, Tuple

import numpy as np

from edygs_ns.geometry import POSE_SIZE


def load_json(path: Path) -> Dict[str, Any]:
    """Read a JSON object.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is not valid JSON or not an object; the message names the file.
    """
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    try:
        with open(path, encoding="utf-8") as handle:
            data = json.load(handle)
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from err
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object at the top level, found {type(data).__name__}")
    return data


def require_key(meta: Dict[str, Any], key: str, source: Path) -> Any:
    """meta[key], or a ValueError naming the file and the missing key."""
    if key not in meta:
        raise ValueError(f"{source}: missing required key {key!r}")
    return meta[key]


def require_files(paths: Sequence[Path], source: Path) -> None:
    """Raise FileNotFoundError naming the first of ``paths`` that does not exist (listed in ``source``)."""
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise FileNotFoundError(f"{source}: {len(missing)} listed image(s) not found, first: {missing[0]}")


def as_pose(matrix: Any, source: Path, what: str) -> np.ndarray:
    """A 4x4 (or 3x4) nested list as a [4, 4] float64 pose; ValueError naming file and item."""
    arr = np.asarray(matrix, dtype=np.float64)
    if arr.shape == (POSE_SIZE - 1, POSE_SIZE):
        arr = np.concatenate([arr, np.array([[0.0, 0.0, 0.0, 1.0]])], axis=0)
    if arr.shape != (POSE_SIZE, POSE_SIZE) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{source}: {what} is not a finite 4x4 transform matrix (shape {arr.shape})")
    return arr


def numbered_files(folder: Path, pattern: str) -> List[Tuple[int, Path]]:
    """Files in ``folder`` whose name matches ``pattern`` (a regex with one integer group), by number.

    Returns:
        [(number, path)] sorted by number.
    """
    regex = re.compile(pattern)
    found = []
    for path in folder.iterdir() if folder.is_dir() else []:
        match = regex.fullmatch(path.name)
        if match:
            found.append((int(match.group(1)), path))
    return sorted(found)

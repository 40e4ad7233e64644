"""LLFF ``poses_bounds.npy`` files, as E2NeRF's real scenes and EvDeblurNeRF scenes store them.

A row is a 3x5 matrix [R | t | hwf] flattened row-major (15 numbers), then near and far. The
rotation columns are (down, right, back) (:func:`edygs_ns.geometry.llff_to_opengl` reorders them);
hwf is the height, width and focal length (pixels) of the images the poses were computed on.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Tuple

import numpy as np

from edygs_ns.geometry import Intrinsics, llff_to_opengl

#: A 3x5 pose matrix: rows, columns; then the numbers of a row (matrix, near, far).
LLFF_ROWS, LLFF_COLS = 3, 5
POSE_COLUMNS = LLFF_ROWS * LLFF_COLS
LLFF_ROW_LENGTH = POSE_COLUMNS + 2


def load_npy(path: Path, needed_by: str = "the scene") -> np.ndarray:
    """A .npy array (never pickled objects); FileNotFoundError / ValueError naming the file."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found ({needed_by} needs it)")
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as err:
        raise ValueError(f"{path}: cannot read as a .npy array ({err})") from err


def read_rows(path: Path, expected_rows: Optional[int], what: str, needed_by: str = "the scene") -> np.ndarray:
    """float64 [N, 17] LLFF rows from ``path``, checked.

    Args:
        path: the .npy file.
        expected_rows: N required (None: any).
        what: why N rows are expected, for the error.
        needed_by: who needs the file, for the missing-file error.

    Raises:
        FileNotFoundError / ValueError: missing, unreadable, wrongly shaped or non-finite (one
            line naming the file and the fault).
    """
    rows = load_npy(path, needed_by)
    if rows.ndim != 2 or rows.shape[1] != LLFF_ROW_LENGTH:
        raise ValueError(f"{path}: expected LLFF rows of {LLFF_ROW_LENGTH} numbers [N, 17], got shape {rows.shape}")
    if expected_rows is not None and rows.shape[0] != expected_rows:
        raise ValueError(f"{path}: has {rows.shape[0]} rows, expected {expected_rows} ({what}; shape {rows.shape}, "
                         f"expected {(expected_rows, LLFF_ROW_LENGTH)})")
    if not np.all(np.isfinite(rows)):
        raise ValueError(f"{path}: holds non-finite values")
    return rows.astype(np.float64)


def rows_to_c2w(rows: np.ndarray) -> np.ndarray:
    """[N, 4, 4] OpenGL camera-to-world of LLFF rows [N, 17]."""
    return llff_to_opengl(rows[:, :POSE_COLUMNS].reshape(-1, LLFF_ROWS, LLFF_COLS))


def c2w_to_rows(c2w: np.ndarray, height: int, width: int, focal: float, near: float, far: float) -> np.ndarray:
    """OpenGL camera-to-world [N, 4, 4] as LLFF rows [N, 17] (the inverse of :func:`rows_to_c2w`):
    rotation columns (down, right, back), t, hwf = (height, width, focal), then near and far."""
    mats = np.zeros((len(c2w), LLFF_ROWS, LLFF_COLS))
    mats[:, :, 0] = -c2w[:, :3, 1]
    mats[:, :, 1] = c2w[:, :3, 0]
    mats[:, :, 2] = c2w[:, :3, 2]
    mats[:, :, 3] = c2w[:, :3, 3]
    mats[:, :, 4] = [height, width, focal]
    return np.concatenate([mats.reshape(len(c2w), -1), np.tile([near, far], (len(c2w), 1))], axis=1)


def rows_intrinsics(rows: np.ndarray, height: int, width: int) -> Intrinsics:
    """Pinhole camera of the first row's hwf, for stored images of width x height: the focal
    length scaled by width / hwf width, the principal point at the image centre."""
    focal, hwf_width = float(rows[0, 14]), float(rows[0, 9])
    if hwf_width > 0:
        focal *= width / hwf_width
    return Intrinsics(width=width, height=height, fl_x=focal, fl_y=focal, cx=width / 2.0, cy=height / 2.0)


def rows_depth_range(rows: np.ndarray) -> Tuple[float, float]:
    """(smallest near, largest far) over LLFF rows [N, 17]."""
    return float(rows[:, POSE_COLUMNS].min()), float(rows[:, POSE_COLUMNS + 1].max())

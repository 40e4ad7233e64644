"""Evaluation figures written as PNG with matplotlib's Agg canvas (no display, no pyplot state).

- `save_grid`: one row per view, one column per image kind (blurry input | EDI latent | ours |
  ground truth | motion mask ...), column titles on top.
- `plot_trajectories`: camera centres of several trajectories, top-down XY and side XZ views.
- `plot_psnr_over_time`: per-view PSNR against normalised time, one line per method.
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from edygs_ns.io.images import UINT8_MAX

PathLike = Union[str, Path]

#: Output resolution in dots per inch.
DPI = 100
#: Width of one grid cell in inches (height follows the image aspect).
GRID_CELL_WIDTH_IN = 2.0
#: Height of the band holding the column titles, in inches.
GRID_TITLE_HEIGHT_IN = 0.35
#: Width of the band holding the row labels (when given), in inches.
GRID_LABEL_WIDTH_IN = 0.35
#: Font size of titles and labels, in points.
TITLE_FONT_SIZE = 9
#: Size (width, height) in inches of the trajectory figure (two panels) and the PSNR plot.
TRAJECTORY_FIGSIZE_IN = (10.0, 5.0)
PSNR_FIGSIZE_IN = (7.0, 4.0)
#: Marker size (points) of camera centres in the trajectory plot.
TRAJECTORY_MARKER_SIZE = 3.0
#: Trajectory projections drawn: (panel title, horizontal axis index, vertical axis index).
TRAJECTORY_PROJECTIONS: Tuple[Tuple[str, int, int], ...] = (("top-down (x, y)", 0, 1), ("side (x, z)", 0, 2))
AXIS_NAMES = ("x", "y", "z")


def _display_image(image: np.ndarray, where: str) -> Tuple[np.ndarray, bool]:
    """Image as float [H, W, 3] in [0, 1], or [H, W] grey (second value True) for masks."""
    arr = np.asarray(image)
    if arr.dtype == np.uint8:
        arr = arr.astype(np.float32) / UINT8_MAX
    else:
        arr = arr.astype(np.float32)
    if arr.ndim == 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if arr.ndim == 3 and arr.shape[-1] == 4:
        arr = arr[..., :3]
    if arr.ndim == 2:
        return np.clip(arr, 0.0, 1.0), True
    if arr.ndim == 3 and arr.shape[-1] == 3:
        return np.clip(arr, 0.0, 1.0), False
    raise ValueError(f"save_grid: {where} has shape {np.asarray(image).shape}, expected [H, W], [H, W, 1], [H, W, 3] or [H, W, 4]")


def _finish(fig: Figure, path: PathLike) -> Path:
    """Render `fig` with the Agg canvas into the PNG `path` (parent folders created)."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig)
    fig.savefig(out, dpi=DPI, format="png")
    return out


def grid_size_px(n_rows: int, n_cols: int, image_hw: Tuple[int, int], row_labels: bool = False) -> Tuple[int, int]:
    """(width, height) in pixels of the PNG `save_grid` writes for this layout."""
    width_in, height_in, _ = _grid_layout(n_rows, n_cols, image_hw, row_labels)
    return int(round(width_in * DPI)), int(round(height_in * DPI))


def _grid_layout(n_rows: int, n_cols: int, image_hw: Tuple[int, int], row_labels: bool) -> Tuple[float, float, float]:
    cell_h = GRID_CELL_WIDTH_IN * image_hw[0] / image_hw[1]
    label_w = GRID_LABEL_WIDTH_IN if row_labels else 0.0
    return label_w + n_cols * GRID_CELL_WIDTH_IN, GRID_TITLE_HEIGHT_IN + n_rows * cell_h, cell_h


def save_grid(
    path: PathLike,
    rows: Sequence[Mapping[str, np.ndarray]],
    columns: Sequence[str],
    row_labels: Optional[Sequence[str]] = None,
) -> Path:
    """Write a side-by-side image grid, one row per view, with column titles.

    Args:
        path: output PNG file.
        rows: one dict per view, column title -> image. Images are [H, W, 3] (or RGBA, the
            alpha dropped) float in [0, 1] or uint8; [H, W] or [H, W, 1] arrays are masks and
            drawn in grey (0 black, 1 white). A column missing from a row leaves its cell blank.
            The first image fixes the cell aspect ratio.
        columns: column titles, left to right (e.g. "blurry input", "EDI latent", "ours",
            "ground truth", "motion mask").
        row_labels: optional text per row, written vertically at the left.

    Returns:
        The PNG path; its size is `grid_size_px(len(rows), len(columns), (H, W), ...)`.
    """
    if not rows or not columns:
        raise ValueError(f"save_grid({path}): needs at least one row and one column, got {len(rows)} rows, {len(columns)} columns")
    if row_labels is not None and len(row_labels) != len(rows):
        raise ValueError(f"save_grid({path}): {len(row_labels)} row labels for {len(rows)} rows")
    for r, row in enumerate(rows):
        unknown = sorted(set(row) - set(columns))
        if unknown:
            raise ValueError(f"save_grid({path}): row {r} has images for unknown columns {unknown}; columns are {list(columns)}")
    first = next((np.asarray(row[c]) for row in rows for c in columns if c in row), None)
    if first is None:
        raise ValueError(f"save_grid({path}): no row holds any image")
    image_hw = (int(first.shape[0]), int(first.shape[1]))
    label_w = GRID_LABEL_WIDTH_IN if row_labels is not None else 0.0
    fig_w, fig_h, cell_h = _grid_layout(len(rows), len(columns), image_hw, row_labels is not None)
    fig = Figure(figsize=(fig_w, fig_h), dpi=DPI)
    for c, title in enumerate(columns):
        x_centre = (label_w + (c + 0.5) * GRID_CELL_WIDTH_IN) / fig_w
        y_centre = 1.0 - 0.5 * GRID_TITLE_HEIGHT_IN / fig_h
        fig.text(x_centre, y_centre, title, ha="center", va="center", fontsize=TITLE_FONT_SIZE)
    for r, row in enumerate(rows):
        bottom = (fig_h - GRID_TITLE_HEIGHT_IN - (r + 1) * cell_h) / fig_h
        if row_labels is not None:
            fig.text(0.5 * label_w / fig_w, bottom + 0.5 * cell_h / fig_h, row_labels[r], rotation=90,
                     ha="center", va="center", fontsize=TITLE_FONT_SIZE)
        for c, title in enumerate(columns):
            left = (label_w + c * GRID_CELL_WIDTH_IN) / fig_w
            ax = fig.add_axes((left, bottom, GRID_CELL_WIDTH_IN / fig_w, cell_h / fig_h))
            ax.set_axis_off()
            if title not in row:
                continue
            img, grey = _display_image(row[title], f"row {r}, column {title!r}")
            if grey:
                ax.imshow(img, cmap="gray", vmin=0.0, vmax=1.0, interpolation="nearest")
            else:
                ax.imshow(img, interpolation="nearest")
    return _finish(fig, path)


def _centres(poses: np.ndarray, name: str) -> np.ndarray:
    """Camera centres [N, 3] from [N, 4, 4] (or [N, 3, 4]) camera-to-world poses or [N, 3] points."""
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim == 3 and arr.shape[1:] in ((4, 4), (3, 4)):
        return arr[:, :3, 3]
    if arr.ndim == 2 and arr.shape[1] == 3:
        return arr
    raise ValueError(f"plot_trajectories: trajectory {name!r} has shape {arr.shape}, expected [N, 4, 4] or [N, 3]")


def plot_trajectories(path: PathLike, trajectories: Mapping[str, np.ndarray], title: Optional[str] = None) -> Path:
    """Plot camera centres of several trajectories in two projections, with a legend.

    Args:
        path: output PNG file.
        trajectories: label -> [N, 4, 4] camera-to-world poses (or [N, 3] centres), e.g.
            {"GT": ..., "initial": ..., "refined": ...}; align them first (trajectory.align_poses).
        title: optional figure title.

    Returns:
        The PNG path (TRAJECTORY_FIGSIZE_IN * DPI pixels).
    """
    if not trajectories:
        raise ValueError(f"plot_trajectories({path}): no trajectory given")
    centres: Dict[str, np.ndarray] = {name: _centres(poses, name) for name, poses in trajectories.items()}
    fig = Figure(figsize=TRAJECTORY_FIGSIZE_IN, dpi=DPI)
    axes = fig.subplots(1, len(TRAJECTORY_PROJECTIONS))
    for ax, (panel, i, j) in zip(axes, TRAJECTORY_PROJECTIONS):
        for name, pts in centres.items():
            ax.plot(pts[:, i], pts[:, j], marker="o", markersize=TRAJECTORY_MARKER_SIZE, label=name)
        ax.set_xlabel(AXIS_NAMES[i])
        ax.set_ylabel(AXIS_NAMES[j])
        ax.set_title(panel, fontsize=TITLE_FONT_SIZE)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True)
    axes[0].legend(fontsize=TITLE_FONT_SIZE)
    if title:
        fig.suptitle(title, fontsize=TITLE_FONT_SIZE)
    fig.tight_layout()
    return _finish(fig, path)


def plot_psnr_over_time(
    path: PathLike, times: Sequence[float], psnr_by_method: Mapping[str, Sequence[float]], title: Optional[str] = None
) -> Path:
    """Plot per-view PSNR (dB) against time, one line per method.

    Args:
        path: output PNG file.
        times: [V] view times (normalised to [0, 1] over the clip).
        psnr_by_method: method -> [V] PSNR in dB, same order as `times`; infinite values
            (perfect views) are left out of the line.
        title: optional plot title.

    Returns:
        The PNG path (PSNR_FIGSIZE_IN * DPI pixels).
    """
    t = np.asarray(times, dtype=np.float64)
    if t.ndim != 1 or t.size == 0:
        raise ValueError(f"plot_psnr_over_time({path}): times has shape {t.shape}, expected [V] with V >= 1")
    if not psnr_by_method:
        raise ValueError(f"plot_psnr_over_time({path}): no method given")
    order = np.argsort(t, kind="stable")
    fig = Figure(figsize=PSNR_FIGSIZE_IN, dpi=DPI)
    ax = fig.subplots()
    for name, values in psnr_by_method.items():
        v = np.asarray(values, dtype=np.float64)
        if v.shape != t.shape:
            raise ValueError(f"plot_psnr_over_time({path}): method {name!r} has {v.shape} values, times has {t.shape}")
        v = np.where(np.isfinite(v), v, np.nan)
        ax.plot(t[order], v[order], marker="o", markersize=TRAJECTORY_MARKER_SIZE, label=name)
    ax.set_xlabel("time (normalised)")
    ax.set_ylabel("PSNR (dB)")
    if title:
        ax.set_title(title, fontsize=TITLE_FONT_SIZE)
    ax.grid(True)
    ax.legend(fontsize=TITLE_FONT_SIZE)
    fig.tight_layout()
    return _finish(fig, path)


__all__: List[str] = ["save_grid", "grid_size_px", "plot_trajectories", "plot_psnr_over_time"]

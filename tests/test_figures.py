"""Tests for the evaluation outputs: edygs_ns.eval.figures (PNG figures) and edygs_ns.eval.report."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from PIL import Image

from edygs_ns.eval.figures import DPI, PSNR_FIGSIZE_IN, TRAJECTORY_FIGSIZE_IN, grid_size_px, plot_psnr_over_time, plot_trajectories, save_grid
from edygs_ns.eval.report import LPIPS_UNAVAILABLE_TEXT, write_metrics

H, W = 24, 32
COLUMNS = ["blurry input", "EDI latent", "ours", "ground truth", "motion mask"]


def _row(value: float) -> dict:
    rgb = np.zeros((H, W, 3), np.float32)
    rgb[..., 0] = 1.0  # pure red
    return {
        "blurry input": (rgb * 255).astype(np.uint8),
        "EDI latent": np.full((H, W, 3), value, np.float32),
        "ours": rgb,
        "ground truth": np.full((H, W, 3), 1.0 - value, np.float32),
        "motion mask": np.ones((H, W), np.float32),  # a mask: drawn white
    }


def _read(path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"))


def test_save_grid_size_and_cell_contents(tmp_path):
    rows = [_row(0.2), _row(0.6)]
    del rows[1]["EDI latent"]  # a missing cell stays blank (white figure background)
    path = save_grid(tmp_path / "grid" / "views.png", rows, COLUMNS, row_labels=["view 0", "view 1"])
    assert path.is_file() and path.stat().st_size > 0
    img = _read(path)
    width, height = grid_size_px(2, len(COLUMNS), (H, W), row_labels=True)
    assert img.shape[:2] == (height, width)
    assert width / height > len(COLUMNS) * W / (2 * H) * 0.8  # wide grid, about 5 cells across 2 rows

    # sample the centre of each cell from the layout constants
    from edygs_ns.eval import figures

    cell_w = figures.GRID_CELL_WIDTH_IN * DPI
    cell_h = cell_w * H / W
    left0 = figures.GRID_LABEL_WIDTH_IN * DPI
    top0 = figures.GRID_TITLE_HEIGHT_IN * DPI

    def centre(r: int, c: int) -> np.ndarray:
        return img[int(top0 + (r + 0.5) * cell_h), int(left0 + (c + 0.5) * cell_w)].astype(int)

    assert tuple(centre(0, 0)) == (255, 0, 0)  # uint8 red
    assert tuple(centre(0, 2)) == (255, 0, 0)  # float red
    assert abs(centre(0, 1)[0] - round(0.2 * 255)) <= 1  # grey level 0.2
    assert abs(centre(0, 3)[0] - round(0.8 * 255)) <= 1
    assert tuple(centre(0, 4)) == (255, 255, 255)  # mask of ones, grey colour map
    assert tuple(centre(1, 1)) == (255, 255, 255)  # missing cell
    # the title band holds dark text pixels
    assert img[: int(top0)].min() < 128


def test_save_grid_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="unknown columns"):
        save_grid(tmp_path / "x.png", [{"typo": np.zeros((H, W, 3))}], COLUMNS)
    with pytest.raises(ValueError, match="shape"):
        save_grid(tmp_path / "x.png", [{"ours": np.zeros((H, W, 5))}], COLUMNS)


def _circle(n: int, radius: float, z: float) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    angles = np.linspace(0.0, math.pi, n)
    poses[:, 0, 3], poses[:, 1, 3], poses[:, 2, 3] = radius * np.cos(angles), radius * np.sin(angles), z
    return poses


def test_plot_trajectories_writes_png_of_expected_size(tmp_path):
    trajectories = {"GT": _circle(10, 1.0, 0.0), "initial": _circle(10, 1.2, 0.1), "refined": _circle(10, 1.02, 0.0)}
    path = plot_trajectories(tmp_path / "traj.png", trajectories, title="trajectories")
    img = _read(path)
    assert img.shape[:2] == (round(TRAJECTORY_FIGSIZE_IN[1] * DPI), round(TRAJECTORY_FIGSIZE_IN[0] * DPI))
    # three differently coloured lines: count strongly saturated colours
    saturated = img[(img.max(axis=2).astype(int) - img.min(axis=2).astype(int)) > 100]
    hues = {tuple(int(v) // 64 for v in px) for px in saturated}
    assert len(hues) >= 3
    with pytest.raises(ValueError, match="initial"):
        plot_trajectories(tmp_path / "bad.png", {"initial": np.zeros((4, 2))})


def test_plot_psnr_over_time(tmp_path):
    times = [0.0, 0.25, 0.5, 0.75, 1.0]
    path = plot_psnr_over_time(tmp_path / "psnr.png", times, {"ours": [30, 31, math.inf, 29, 30], "blurry": [22, 23, 21, 22, 24]})
    img = _read(path)
    assert img.shape[:2] == (round(PSNR_FIGSIZE_IN[1] * DPI), round(PSNR_FIGSIZE_IN[0] * DPI))
    assert img.std() > 0
    with pytest.raises(ValueError, match="blurry"):
        plot_psnr_over_time(tmp_path / "bad.png", times, {"blurry": [1.0, 2.0]})


# ---------------------------------------------------------------- report


def test_write_metrics_json_and_markdown(tmp_path):
    metrics = {
        "edygs": {
            "input views": {
                "psnr": {"mean": 31.84, "std": 0.5, "n": 60},
                "ssim": 0.905,
                "lpips_alex": 0.1923,
                "lpips_vgg": "LPIPS(vgg) needs 'vgg16-397923af.pth'",
                "mask_iou": 0.8,
                "ate": 0.0024,
                "rpe_t": 0.001,
                "rpe_r": 0.05,
                "ate_frac": 0.001,
            },
            "novel views": {"psnr": math.inf, "ssim": 0.8993, "lpips_vgg": None},
        },
        "blurry": {"input views": {"psnr": 24.5}},
    }
    json_path, md_path = write_metrics(tmp_path / "out", metrics)
    data = json.loads(json_path.read_text(encoding="utf-8"))  # strict JSON: no bare Infinity
    assert data["edygs"]["input views"]["ate_frac"] == 0.001
    assert data["edygs"]["novel views"]["psnr"] == "inf"
    assert data["edygs"]["input views"]["psnr"]["n"] == 60

    lines = md_path.read_text(encoding="utf-8").splitlines()
    table = [line for line in lines if line.startswith("|")]
    header = [cell.strip() for cell in table[0].strip("|").split("|")]
    assert header == ["Method", "Split", "PSNR↑", "SSIM↑", "PSNR dyn↑", "PSNR static↑", "PSNR seen↑", "PSNR unseen↑", "error share unseen", "LPIPS(alex)↓", "LPIPS(vgg)↓",
                      "mask IoU↑", "ATE↓", "RPE_t↓", "RPE_r↓"]  # fmt: skip
    rows = [[cell.strip() for cell in line.strip("|").split("|")] for line in table[2:]]
    assert len(rows) == 3
    first = dict(zip(header, rows[0]))
    assert first["Method"] == "edygs" and first["Split"] == "input views"
    assert first["PSNR↑"] == "31.84 ± 0.50"
    assert first["SSIM↑"] == "0.9050"
    assert first["LPIPS(vgg)↓"] == LPIPS_UNAVAILABLE_TEXT
    assert first["ATE↓"] == "0.0024"
    second = dict(zip(header, rows[1]))
    assert second["PSNR↑"] == "inf" and second["LPIPS(vgg)↓"] == "-" and second["mask IoU↑"] == "-"
    assert first["PSNR dyn↑"] == "-"  # not measured: no region PSNR in these rows
    assert dict(zip(header, rows[2]))["Method"] == "blurry"


def test_write_metrics_single_method_has_no_method_column(tmp_path):
    _, md_path = write_metrics(tmp_path, {"edygs": {"novel views": {"psnr": 30.9}}}, notes=())
    table = [line for line in md_path.read_text(encoding="utf-8").splitlines() if line.startswith("|")]
    assert table[0].startswith("| Split | PSNR↑")
    assert "30.90" in table[2]
    with pytest.raises(ValueError, match="edygs"):
        write_metrics(tmp_path, {"edygs": {"novel views": 30.9}})

"""Write evaluation results as `metrics.json` and a markdown table `metrics.md`.

The results are nested method -> split -> metric key -> value, e.g.

    {"edygs": {"input views": {"psnr": 31.8, "ssim": {"mean": 0.905, "std": 0.01, "n": 60},
                               "lpips_vgg": "LPIPS(vgg) needs ... (weights missing)",
                               "ate": 0.0024, "rpe_t": 0.001, "rpe_r": 0.05},
               "novel views": {"psnr": 30.9, ...}}}

A value is a number, a summary dict with "mean" (and optionally "std", "n") as produced by
`MetricSet.summary()`, None (not measured), or a string: the reason it is unavailable (shown as
"n/a", and for LPIPS as "n/a (weights missing)"). Keys outside `COLUMNS` are kept in the JSON
only.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, List, Mapping, Sequence, Tuple, Union

#: (metric key, column header, number format) of the markdown table, left to right.
COLUMNS: Tuple[Tuple[str, str, str], ...] = (
    ("psnr", "PSNR↑", ".2f"),
    ("ssim", "SSIM↑", ".4f"),
    ("psnr_dynamic", "PSNR dyn↑", ".2f"),
    ("psnr_static", "PSNR static↑", ".2f"),
    ("psnr_covisible", "PSNR seen↑", ".2f"),
    ("psnr_unseen", "PSNR unseen↑", ".2f"),
    ("unseen_error_share", "error share unseen", ".2f"),
    ("lpips_alex", "LPIPS(alex)↓", ".4f"),
    ("lpips_vgg", "LPIPS(vgg)↓", ".4f"),
    ("mask_iou", "mask IoU↑", ".4f"),
    ("ate", "ATE↓", ".4g"),
    ("rpe_t", "RPE_t↓", ".4g"),
    ("rpe_r", "RPE_r↓", ".4g"),
)
#: Metric keys whose unavailability means missing LPIPS backbone weights.
LPIPS_KEYS = ("lpips_alex", "lpips_vgg")
#: Cell texts for an unavailable LPIPS, another unavailable metric, and a metric not measured.
LPIPS_UNAVAILABLE_TEXT = "n/a (weights missing)"
UNAVAILABLE_TEXT = "n/a"
NOT_MEASURED_TEXT = "-"
#: Output file names.
JSON_NAME = "metrics.json"
MARKDOWN_NAME = "metrics.md"
#: JSON indentation (spaces).
JSON_INDENT = 2
#: Lines written under the table unless the caller gives its own notes.
DEFAULT_NOTES: Tuple[str, ...] = (
    "ATE: RMSE of camera centres after Sim(3) (Umeyama) alignment; RPE over consecutive frames "
    "after the same alignment. ATE and RPE_t in ground-truth units, RPE_r in degrees.",
    "SSIM: 11x11 Gaussian window, sigma 1.5, zero-padded borders (as the 3DGS metric scripts). LPIPS on images in [0, 1].",
)


def _jsonable(value: Any) -> Any:
    """Copy of `value` that strict JSON accepts: inf -> "inf", nan -> None, numpy -> Python."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if hasattr(value, "item") and callable(value.item):  # numpy / torch scalars
        value = value.item()
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        if math.isnan(value):
            return None
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return value
    raise ValueError(f"write_metrics: cannot store value {value!r} of type {type(value).__name__} in JSON")


def _format_number(value: float, fmt: str) -> str:
    if math.isnan(value):
        return "nan"
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return format(value, fmt)


def format_cell(key: str, value: Any, fmt: str) -> str:
    """Markdown text of one metric value (see the module docstring for accepted values)."""
    if value is None:
        return NOT_MEASURED_TEXT
    if isinstance(value, str):
        return LPIPS_UNAVAILABLE_TEXT if key in LPIPS_KEYS else UNAVAILABLE_TEXT
    if isinstance(value, Mapping):
        if "mean" not in value:
            raise ValueError(f"write_metrics: {key} is a dict without 'mean': {value!r}")
        text = _format_number(float(value["mean"]), fmt)
        std = value.get("std")
        single_view = value.get("n") is not None and value["n"] <= 1
        if std is not None and math.isfinite(float(std)) and not single_view:
            text += " ± " + _format_number(float(std), fmt)
        return text
    return _format_number(float(value), fmt)


def markdown_table(metrics: Mapping[str, Mapping[str, Mapping[str, Any]]]) -> List[str]:
    """Lines of the markdown table: one row per (method, split); a Method column if several."""
    with_method = len(metrics) > 1
    header = (["Method"] if with_method else []) + ["Split"] + [title for _, title, _ in COLUMNS]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(" --- " for _ in header) + "|"]
    for method, splits in metrics.items():
        for split, values in splits.items():
            cells = ([method] if with_method else []) + [split]
            cells += [format_cell(key, values.get(key), fmt) for key, _, fmt in COLUMNS]
            lines.append("| " + " | ".join(cells) + " |")
    return lines


def _validate(metrics: Mapping[str, Any]) -> None:
    if not isinstance(metrics, Mapping) or not metrics:
        raise ValueError("write_metrics: metrics must be a non-empty dict method -> split -> metric -> value")
    for method, splits in metrics.items():
        if not isinstance(splits, Mapping) or not splits:
            raise ValueError(f"write_metrics: metrics[{method!r}] must be a non-empty dict split -> metric -> value")
        for split, values in splits.items():
            if not isinstance(values, Mapping):
                raise ValueError(f"write_metrics: metrics[{method!r}][{split!r}] must be a dict metric -> value, got {type(values).__name__}")


def write_metrics(
    out_dir: Union[str, Path],
    metrics: Mapping[str, Mapping[str, Mapping[str, Any]]],
    notes: Sequence[str] = DEFAULT_NOTES,
    title: str = "Evaluation",
) -> Tuple[Path, Path]:
    """Write `metrics.json` (all values) and `metrics.md` (the table) into `out_dir`.

    Args:
        out_dir: output folder, created if needed.
        metrics: method -> split (e.g. "input views", "novel views") -> metric key -> value;
            keys of the table: psnr, ssim, lpips_alex, lpips_vgg, mask_iou, ate, rpe_t, rpe_r.
        notes: lines written under the table (units, LPIPS backbone, ...).
        title: markdown heading.

    Returns:
        (path of metrics.json, path of metrics.md).
    """
    _validate(metrics)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / JSON_NAME
    md_path = out / MARKDOWN_NAME
    json_path.write_text(json.dumps(_jsonable(metrics), indent=JSON_INDENT, allow_nan=False, ensure_ascii=False) + "\n",
                         encoding="utf-8")
    lines = [f"# {title}", ""] + markdown_table(metrics)
    if notes:
        lines.append("")
        lines += [f"- {note}" for note in notes]
    md_path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return json_path, md_path

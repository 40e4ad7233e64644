"""Adds the ``motion_mask`` property to ``ns-export gaussian-splat`` PLYs of EDyGS runs.

nerfstudio 1.1.5's exporter builds a fixed set of PLY columns from the model's ``means``,
``shs_0``, ``opacities``, ``scales`` and ``quats``, filters rows (crop box, non-finite values,
opacity below 1/255) and hands the columns to ``ExportGaussianSplat.write_ply(filename, count,
columns)``. There is no hook for extra columns, so we wrap that one static method:

* :class:`~edygs_ns.model.splat_export_view.SplatExportView` calls :func:`register_export_source`
  when the exporter reads its ``means``; the first call installs the wrapper (the exporter module
  is loaded by then: it is the running ``ns-export``).
* the wrapper finds, for every row the exporter kept, the Gaussian it came from: rows are kept in
  order and their centres are exact float32 copies of ``means``, so each exported (x, y, z) is
  looked up among the model's centres. It then adds ``motion_mask`` (m in [0, 1]) for those rows.
* any other model's export is passed through unchanged; if some row cannot be matched, the PLY is
  written without the column and a warning says so.
"""

from __future__ import annotations

import sys
import weakref
from collections import OrderedDict
from typing import Any, Callable, Optional

import numpy as np
from nerfstudio.utils.rich_utils import CONSOLE

#: Name of the extra per-Gaussian PLY property holding the motion-mask value.
MOTION_MASK_PROPERTY = "motion_mask"
#: The module of ``ns-export``.
EXPORTER_MODULE = "nerfstudio.scripts.exporter"
#: Attribute marking our wrapper (so it is installed once).
WRAPPED_FLAG = "_edygs_motion_mask"

_source: Optional["weakref.ReferenceType[Any]"] = None


def register_export_source(model: Any) -> None:
    """Remember `model` as the one being exported and install the write_ply wrapper if the
    exporter is running (idempotent)."""
    global _source
    _source = weakref.ref(model)
    exporter = sys.modules.get(EXPORTER_MODULE)
    splat = getattr(exporter, "ExportGaussianSplat", None)
    if splat is None or getattr(splat.write_ply, WRAPPED_FLAG, False):
        return
    splat.write_ply = staticmethod(_wrap(splat.write_ply))


def exported_rows(model_xyz: np.ndarray, exported_xyz: np.ndarray) -> Optional[np.ndarray]:
    """Index into `model_xyz` [N, 3] of every row of `exported_xyz` [M, 3] (exact float32 match),
    or None when some exported row is not among the model's centres."""
    if len(model_xyz) == 0:
        return None if len(exported_xyz) else np.zeros(0, dtype=np.int64)
    model_keys = np.ascontiguousarray(model_xyz, dtype=np.float32).view(np.dtype((np.void, 12))).ravel()
    exported_keys = np.ascontiguousarray(exported_xyz, dtype=np.float32).view(np.dtype((np.void, 12))).ravel()
    order = np.argsort(model_keys, kind="stable")
    pos = np.searchsorted(model_keys[order], exported_keys)
    pos = np.minimum(pos, len(order) - 1)
    rows = order[pos]
    if not np.array_equal(model_keys[rows], exported_keys):
        return None
    return rows


def _wrap(write_ply: Callable[..., Any]) -> Callable[..., Any]:
    def write_ply_with_mask(filename: str, count: int, map_to_tensors: "OrderedDict[str, np.ndarray]") -> Any:
        model = _source() if _source is not None else None
        if model is not None and MOTION_MASK_PROPERTY not in map_to_tensors and {"x", "y", "z"} <= set(map_to_tensors):
            baked = model._baked()  # the export's own bake (SplatExportView caches it)
            exported = np.stack([np.asarray(map_to_tensors[a]).reshape(-1) for a in ("x", "y", "z")], axis=1)
            rows = exported_rows(baked["means"].cpu().numpy(), exported)
            if rows is None:
                CONSOLE.print(f"[yellow]ns-export: could not match the exported rows to the model; {filename} has no {MOTION_MASK_PROPERTY}")
            else:
                map_to_tensors[MOTION_MASK_PROPERTY] = baked["mask"].cpu().numpy()[rows].astype(np.float32)
        return write_ply(filename, count, map_to_tensors)

    setattr(write_ply_with_mask, WRAPPED_FLAG, True)
    return write_ply_with_mask


__all__ = ["MOTION_MASK_PROPERTY", "register_export_source", "exported_rows"]

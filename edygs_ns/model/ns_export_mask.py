"""Adds the ``motion_mask`` property to ``ns-export gaussian-splat`` PLYs of EDyGS runs.

nerfstudio 1.1.5's exporter builds a fixed set of PLY columns from the model's ``means``,
``shs_0``, ``opacities``, ``scales`` and ``quats``, filters rows (crop box, non-finite values,
opacity below 1/255) and hands the columns to ``ExportGaussianSplat.write_ply(filename, count,
columns)``. There is no hook for extra columns, so we wrap that one static method:

* :func:`install` runs once, when the plugin loads (``configs/method_configs.py``, the entry point
  nerfstudio imports). The exporter module is not imported by then in general: ``ns-train`` never
  imports it (it costs about a second, open3d), and under ``ns-export`` it is the exporter's own
  imports that load the plugin, before ``ExportGaussianSplat`` is defined. So the wrapper goes on
  when the class exists: at once if the module is loaded, on the first read of the module from
  outside once it is (``ns-export`` reads ``entrypoint`` from it) if it is being loaded, and right
  after its import (a ``sys.meta_path`` finder) if it is not loaded yet.
* the model to take the mask from is the last EDyGS model built (:func:`set_export_source`, called
  by :class:`~edygs_ns.model.splat_export_view.SplatExportView`; ``ns-export`` builds one).
* the wrapper finds, for every row the exporter kept, the Gaussian it came from: rows are kept in
  order and their centres are exact float32 copies of ``means``, so each exported (x, y, z) is
  looked up among the model's centres. It then adds ``motion_mask`` (m in [0, 1]) for those rows.
* any other model's export is passed through unchanged; if some row cannot be matched, the PLY is
  written without the column and a warning says so.
"""

from __future__ import annotations

import importlib.abc
import importlib.util
import sys
import types
import weakref
from collections import OrderedDict
from typing import Any, Callable, Dict, Optional

import numpy as np
from nerfstudio.utils.rich_utils import CONSOLE

#: Name of the extra per-Gaussian PLY property holding the motion-mask value.
MOTION_MASK_PROPERTY = "motion_mask"
#: The module of ``ns-export``.
EXPORTER_MODULE = "nerfstudio.scripts.exporter"
#: Attribute marking our wrapper (so it is installed once).
WRAPPED_FLAG = "_edygs_motion_mask"

_source: Optional["weakref.ReferenceType[Any]"] = None


def set_export_source(model: Any) -> None:
    """Remember ``model`` as the one an export in this process takes the motion mask from."""
    global _source
    _source = weakref.ref(model)


def install() -> None:
    """Wrap ``ExportGaussianSplat.write_ply`` now or as soon as it exists (idempotent)."""
    module = sys.modules.get(EXPORTER_MODULE)
    if module is None:
        if not any(isinstance(finder, _WrapAfterImport) for finder in sys.meta_path):
            sys.meta_path.insert(0, _WrapAfterImport())
    elif not _wrap_exporter(vars(module)):
        module.__class__ = _WrapOnFirstRead


def is_installed() -> bool:
    """Whether the exporter is loaded and its write_ply wrapped."""
    splat = getattr(sys.modules.get(EXPORTER_MODULE), "ExportGaussianSplat", None)
    return splat is not None and getattr(splat.write_ply, WRAPPED_FLAG, False)


def _wrap_exporter(namespace: Dict[str, Any]) -> bool:
    """Wrap write_ply of the exporter module with globals ``namespace``; False: not defined yet."""
    splat = namespace.get("ExportGaussianSplat")
    if splat is None:
        return False
    if not getattr(splat.write_ply, WRAPPED_FLAG, False):
        splat.write_ply = staticmethod(_wrap(splat.write_ply))
    return True


class _WrapOnFirstRead(types.ModuleType):
    """Class of the exporter module while it is being imported: the first read of one of its
    attributes from outside after ``ExportGaussianSplat`` is defined wraps it, and the module
    becomes a plain module again (reads inside the module body do not come here)."""

    def __getattribute__(self, name: str) -> Any:
        if _wrap_exporter(types.ModuleType.__getattribute__(self, "__dict__")):
            self.__class__ = types.ModuleType
        return types.ModuleType.__getattribute__(self, name)


class _WrapAfterImport(importlib.abc.MetaPathFinder):
    """Finds the exporter module with the other finders and wraps it once its code has run."""

    def __init__(self) -> None:
        self._finding = False

    def find_spec(self, fullname: str, path: Any, target: Any = None) -> Any:
        if fullname != EXPORTER_MODULE or self._finding:
            return None
        self._finding = True
        try:
            spec = importlib.util.find_spec(fullname)
        finally:
            self._finding = False
        if spec is None or spec.loader is None:
            return spec
        exec_module = spec.loader.exec_module

        def exec_and_wrap(module: types.ModuleType) -> None:
            exec_module(module)
            _wrap_exporter(vars(module))

        spec.loader.exec_module = exec_and_wrap  # type: ignore[method-assign]
        return spec


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


__all__ = ["MOTION_MASK_PROPERTY", "install", "is_installed", "set_export_source", "exported_rows"]

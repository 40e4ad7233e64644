"""Fixes for host-framework traps, applied when nerfstudio imports our method config.

nerfstudio 1.1.5 calls ``torch.load(path)`` on its own checkpoints; with torch >= 2.6 the default
``weights_only=True`` refuses the numpy scalars that its scheduler state holds
(``UnpicklingError``), which breaks ``--load-dir`` resume, ``ns-render``, ``ns-viewer``,
``ns-eval`` and ``ns-export``. We allow exactly those numpy types in the weights-only
unpickler instead of turning the safety check off.
"""

from __future__ import annotations

import numpy as np
import torch

_APPLIED = False


def _numpy_checkpoint_globals() -> list:
    """The numpy objects that nerfstudio checkpoints pickle (scalars and their dtypes)."""
    try:
        from numpy.core.multiarray import scalar  # numpy < 2
    except ImportError:  # pragma: no cover - numpy 2 layout
        from numpy._core.multiarray import scalar  # type: ignore[no-redef]
    allowed: list = [scalar, np.dtype]
    for name in ("Float64DType", "Float32DType", "Int64DType", "Int32DType", "BoolDType"):
        dtype_class = getattr(getattr(np, "dtypes", None), name, None)
        if dtype_class is not None:
            allowed.append(dtype_class)
    return allowed


def allow_nerfstudio_checkpoints() -> None:
    """Let ``torch.load(..., weights_only=True)`` read nerfstudio checkpoints (idempotent)."""
    global _APPLIED
    if _APPLIED:
        return
    add_safe_globals = getattr(torch.serialization, "add_safe_globals", None)
    if add_safe_globals is not None:
        add_safe_globals(_numpy_checkpoint_globals())
    _APPLIED = True

"""The one rendering contract that every rasteriser backend implements.

Shapes: N Gaussians, C cameras, D feature channels, H x W pixels. The Gaussians' geometry
(means, quats, scales) is either shared by the C cameras ([N, ·]) or given per camera
([C, N, ·]: e.g. deformed at each camera's time, so a training pair renders in one call).
Cameras use the OpenCV convention (x right, y down, z forward) for `viewmats` (world-to-camera).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Protocol

import torch
from torch import Tensor

#: gsplat's compositing rules, shared by every backend.
#: gsplat 1.4.0's kernels clamp alpha at 0.999 (3DGS used 0.99); the CPU backend must match it.
ALPHA_MAX = 0.999
ALPHA_MIN = 1.0 / 255.0
TRANSMITTANCE_MIN = 1e-4
LOW_PASS_EPS = 0.3
DEFAULT_NEAR = 0.01
DEFAULT_FAR = 1e10


@dataclass
class RasterOutputs:
    """What a backend returns.

    Attributes:
        render: [C, H, W, D] alpha-composited features (background added as (1 - alpha) * bg).
        depth: [C, H, W, 1] expected depth (alpha-weighted z, divided by alpha where alpha > 0).
        alpha: [C, H, W, 1] accumulated opacity.
        means2d: [C, N, 2] screen-space centres in pixels; a leaf-like tensor whose `.grad`
            after backward holds the densification gradient (the backend calls retain_grad()).
        radii: [C, N] int32 screen radius in pixels, 0 where culled.
        visible: [C, N] bool, radii > 0.
    """

    render: Tensor
    depth: Tensor
    alpha: Tensor
    means2d: Tensor
    radii: Tensor
    visible: Tensor


class RasterBackend(Protocol):
    """Signature of every backend (torch reference in torch_backend, compiled CPU in cpu_backend,
    CUDA in gsplat_backend).

    Args:
        means: [N, 3] world positions. quats: [N, 4] wxyz, need not be normalised. scales: [N, 3]
            activated (positive), world units; or [C, N, ·] each: Gaussians per camera (projected
            per camera, composited together).
        opacities: [N] activated, in (0, 1). features: [N, D] or [C, N, D] colours or other
            channels, already evaluated, any D.
        viewmats: [C, 4, 4] world-to-camera (OpenCV). Ks: [C, 3, 3] pixel intrinsics.
        width, height: image size in pixels.
        backgrounds: [C, D] colour behind the Gaussians, or None for zeros.
        near_plane, far_plane: depth range in world units.

    Returns:
        RasterOutputs; ``means2d.grad`` holds dL/d(pixel centre) after backward.
    """

    def __call__(
        self,
        means: Tensor,
        quats: Tensor,
        scales: Tensor,
        opacities: Tensor,
        features: Tensor,
        viewmats: Tensor,
        Ks: Tensor,
        width: int,
        height: int,
        backgrounds: Optional[Tensor] = None,
        near_plane: float = DEFAULT_NEAR,
        far_plane: float = DEFAULT_FAR,
    ) -> RasterOutputs: ...


def check_inputs(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, features: Tensor,
                 viewmats: Tensor, Ks: Tensor) -> None:
    """Raise ValueError naming the argument whose shape breaks the contract."""
    n = means.shape[-2] if means.dim() >= 2 else -1
    lead = tuple(means.shape[:-2]) if means.dim() == 3 else ()
    expect = {
        "means": (means, (*lead, n, 3)),
        "quats": (quats, (*lead, n, 4)),
        "scales": (scales, (*lead, n, 3)),
        "opacities": (opacities, (n,)),
    }
    for name, (tensor, shape) in expect.items():
        if tuple(tensor.shape) != shape:
            raise ValueError(f"rasterize: {name} has shape {tuple(tensor.shape)}, expected {shape}")
    if features.dim() not in (2, 3) or features.shape[-2] != n:
        raise ValueError(f"rasterize: features has shape {tuple(features.shape)}, expected [N={n}, D] or [C, N, D]")
    c = viewmats.shape[0]
    if tuple(viewmats.shape) != (c, 4, 4):
        raise ValueError(f"rasterize: viewmats has shape {tuple(viewmats.shape)}, expected [C, 4, 4]")
    if tuple(Ks.shape) != (c, 3, 3):
        raise ValueError(f"rasterize: Ks has shape {tuple(Ks.shape)}, expected [C={c}, 3, 3]")
    if features.dim() == 3 and features.shape[0] != c:
        raise ValueError(f"rasterize: features has {features.shape[0]} cameras, viewmats has {c}")
    if lead and lead[0] != c:
        raise ValueError(f"rasterize: means has {lead[0]} cameras, viewmats has {c}")


def select_backend(device: torch.device, force: Optional[str] = None) -> RasterBackend:
    """The backend for tensors on `device`: gsplat on CUDA, the compiled CPU rasteriser on the CPU
    (the torch reference when it cannot be built, after a one-line notice), torch elsewhere.

    Args:
        force: "torch", "cpu" or "gsplat" to override the choice (config field `rasterizer`);
            "torch" runs the torch reference rasteriser on any device, CUDA tensors included;
            "cpu" the compiled one (CPU tensors only).

    Raises:
        GsplatUnavailableError: gsplat on CUDA, and its kernels are neither built nor buildable
            (one line naming the fix: ``edygs-doctor --build-gsplat`` or ``rasterizer torch``);
            checked once per process, before the first gsplat call.
        RuntimeError: "cpu" forced and the compiled rasteriser cannot be built (one line).
        ValueError: an unknown name, or "cpu" for tensors that are not on the CPU.
    """
    kind = torch.device(device).type
    name = force if force not in (None, "auto") else ("gsplat" if kind == "cuda" else "cpu" if kind == "cpu" else "torch")
    if name == "gsplat":
        if kind == "cuda":
            from edygs_ns.cuda_setup import require_gsplat_kernels

            require_gsplat_kernels()
        from edygs_ns.render.gsplat_backend import rasterize_gsplat

        return rasterize_gsplat
    if name == "cpu":
        if kind != "cpu":
            raise ValueError(f"rasterizer 'cpu' runs on CPU tensors, these are on {device}; choose 'auto' or 'torch'")
        from edygs_ns.render.cpu_backend import compiled_available, rasterize_cpu

        if compiled_available():
            return rasterize_cpu
        if force == "cpu":
            raise RuntimeError("the compiled CPU rasteriser cannot be built here (see the notice above); "
                               "train with --pipeline.model.rasterizer torch")
        name = "torch"  # "auto": the notice was logged once by load_extension
    if name == "torch":
        from edygs_ns.render.torch_backend import rasterize_torch

        return rasterize_torch
    raise ValueError(f"unknown rasterizer backend {name!r}; choose 'auto', 'torch', 'cpu' or 'gsplat'")

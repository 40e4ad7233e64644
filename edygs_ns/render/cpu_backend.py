"""The compiled CPU rasteriser: projection, tile binning and compositing in C++ (``csrc/raster_cpu.cpp``).

Two autograd Functions, each with a compiled forward and backward, multi-threaded with OpenMP:
the per-Gaussian EWA projection (``_CompiledProjection``: the expressions and rules of
``projection.py``, closed-form backward to means, quaternions, scales and the world-to-camera
matrices, so pose refinement works; the torch projection under autograd when Ks needs a
gradient), and the per-pixel work (``_CompiledRaster``: tile binning, front-to-back compositing
of D features + depth + alpha, and its backward). ``means2d`` stays the non-leaf tensor between
the two whose ``.grad`` densification reads. The rules (tiles, alpha clamp and cut-off,
transmittance stop) are those of ``torch_backend.py``, the reference the parity tests compare
against. Why this split and toolchain: docs/cpu_rasterizer.md.
"""

from __future__ import annotations

from typing import List, Optional, Tuple

import torch
from jaxtyping import Float
from torch import Tensor

from edygs_ns.render.compiled import load_extension
from edygs_ns.render.contract import (
    ALPHA_MAX,
    ALPHA_MIN,
    DEFAULT_FAR,
    DEFAULT_NEAR,
    LOW_PASS_EPS,
    TRANSMITTANCE_MIN,
    RasterOutputs,
    check_inputs,
)
from edygs_ns.render.projection import Projection, project_gaussians, project_per_camera
from edygs_ns.render.torch_backend import CULL_MARGIN, MIN_ALPHA_FOR_DEPTH, MIN_OPACITY, TILE_SIZE

#: the compositing rules handed to the kernel, in its order.
RULES: List[float] = [ALPHA_MAX, ALPHA_MIN, TRANSMITTANCE_MIN, CULL_MARGIN, MIN_OPACITY]


def compiled_available() -> bool:
    """Whether the C++ kernel is built (or builds now) on this machine."""
    return load_extension() is not None


class _CompiledRaster(torch.autograd.Function):
    """Composited features [C, H, W, D], depth sum and alpha [C, H, W, 1]; backward in C++ to the inputs."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx, means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, depths: Tensor,
        radii: Tensor, size: tuple,
    ) -> Tuple[Tensor, Tensor, Tensor]:
        ext = load_extension()
        width, height, tile = size
        inputs = [t.detach().contiguous() for t in (means2d, conics, opacities, features, depths)]
        # saved: tile offsets and lists, composited flags, per-pixel stops, depth order, packed records, rows
        colour, depth_sum, alpha, *saved = ext.forward(*inputs, radii.contiguous(), width, height, tile, RULES)
        ctx.size = size
        ctx.save_for_backward(*inputs, radii, colour, depth_sum, alpha, *saved)
        return colour, depth_sum, alpha

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grad_outs: Optional[Tensor]):  # type: ignore[override]
        tensors = ctx.saved_tensors
        inputs, radii, outs, saved = tensors[:5], tensors[5], list(tensors[6:9]), list(tensors[9:])
        grads_in = [torch.zeros_like(o) if g is None else g.contiguous() for g, o in zip(grad_outs, outs)]
        width, height, tile = ctx.size
        grads = load_extension().backward(
            *inputs, radii.contiguous(), width, height, tile, RULES, saved, outs, grads_in,
        )
        return (*grads, None, None)


class _CompiledProjection(torch.autograd.Function):
    """``projection.project_gaussians`` in C++ (same rules and expressions); backward in closed form
    to means, quats, scales and viewmats (not Ks)."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx, means: Tensor, quats: Tensor, scales: Tensor, viewmats: Tensor, Ks: Tensor, settings: List[float]
    ) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
        inputs = [t.detach().contiguous() for t in (means, quats, scales, viewmats, Ks)]
        means2d, conics, depths, radii = load_extension().project_forward(*inputs, settings)
        ctx.settings = settings
        ctx.save_for_backward(*inputs)
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, radii

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(  # type: ignore[override]
        ctx, g_means2d: Tensor, g_conics: Tensor, g_depths: Tensor, _g_radii: Optional[Tensor]
    ):
        grads = load_extension().project_backward(
            *ctx.saved_tensors, ctx.settings, g_means2d.contiguous(), g_conics.contiguous(), g_depths.contiguous()
        )
        return (*grads, None, None)


def project_compiled(
    means: Tensor, quats: Tensor, scales: Tensor, viewmats: Tensor, Ks: Tensor, width: int, height: int,
    near_plane: float = DEFAULT_NEAR, far_plane: float = DEFAULT_FAR,
) -> Projection:
    """``project_gaussians`` with the compiled projection; the torch one (under autograd) when Ks
    needs a gradient, which the compiled backward does not give. Shapes and units: ``Projection``."""
    if Ks.requires_grad and torch.is_grad_enabled():
        return project_gaussians(means, quats, scales, viewmats, Ks, width, height, near_plane, far_plane)
    settings = [float(width), float(height), float(near_plane), float(far_plane), LOW_PASS_EPS]
    means2d, conics, depths, radii = _CompiledProjection.apply(means, quats, scales, viewmats, Ks, settings)
    return Projection(means2d=means2d, conics=conics, depths=depths, radii=radii)


def rasterize_cpu(
    means: Float[Tensor, "N 3"],
    quats: Float[Tensor, "N 4"],
    scales: Float[Tensor, "N 3"],
    opacities: Float[Tensor, "N"],
    features: Tensor,
    viewmats: Float[Tensor, "C 4 4"],
    Ks: Float[Tensor, "C 3 3"],
    width: int,
    height: int,
    backgrounds: Optional[Float[Tensor, "C D"]] = None,
    near_plane: float = DEFAULT_NEAR,
    far_plane: float = DEFAULT_FAR,
) -> RasterOutputs:
    """Differentiable CPU rasteriser, compiled; same rules as ``rasterize_torch``. Arguments and
    their shapes and units: ``contract.RasterBackend`` (Gaussians per camera [C, N, ·] are
    projected camera by camera and composited in one call).

    Returns:
        RasterOutputs; gradients reach means, quats, scales, opacities, features and viewmats,
        and ``means2d.grad`` holds dL/d(pixel centre) after backward.

    Raises:
        RuntimeError: the extension is not built (check ``compiled_available()`` first).
    """
    check_inputs(means, quats, scales, opacities, features, viewmats, Ks)
    if means.device.type != "cpu":
        raise ValueError(f"rasterize_cpu: tensors are on {means.device}, the compiled rasteriser runs on the CPU")
    if load_extension() is None:
        raise RuntimeError("rasterize_cpu: the compiled CPU rasteriser is not built; use rasterize_torch")
    n_cams, n_channels = viewmats.shape[0], features.shape[-1]
    if backgrounds is not None and tuple(backgrounds.shape) != (n_cams, n_channels):
        raise ValueError(
            f"rasterize: backgrounds has shape {tuple(backgrounds.shape)}, expected [C={n_cams}, D={n_channels}]"
        )
    proj = project_per_camera(project_compiled, means, quats, scales, viewmats, Ks, width, height, near_plane, far_plane)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    dtype = means2d.dtype
    colour, depth_sum, alpha = _CompiledRaster.apply(
        means2d, proj.conics, opacities.to(dtype), features.to(dtype), proj.depths, proj.radii,
        (width, height, TILE_SIZE),
    )
    if backgrounds is not None:
        colour = colour + (1.0 - alpha) * backgrounds[:, None, None, :]
    depth = depth_sum / alpha.clamp(min=MIN_ALPHA_FOR_DEPTH)
    return RasterOutputs(
        render=colour, depth=depth, alpha=alpha, means2d=means2d, radii=proj.radii, visible=proj.radii > 0
    )

"""The CUDA backend: gsplat 1.4.0's rasterization behind the one rendering contract.

gsplat is imported inside the function, so CPU-only use never loads (or JIT-compiles) its CUDA
extension. All feature channels (RGB plus extras such as the motion mask) and the expected depth
are rendered in one pass ("RGB+ED"). gsplat 1.4.0's ``rasterization`` takes Gaussians shared by
the cameras only; Gaussians per camera ([C, N, ·], a training pair at two times) are projected
camera by camera with its ``fully_fused_projection`` and then binned and composited in one call,
the steps ``rasterization`` runs (packed=False, classic, no SH), so ``means2d`` is the tensor the
compositing reads and its ``.grad`` is the densification gradient.
"""

from __future__ import annotations

import math
from typing import Optional

import torch
from jaxtyping import Float
from torch import Tensor

from edygs_ns.render.contract import DEFAULT_FAR, DEFAULT_NEAR, LOW_PASS_EPS, RasterOutputs, check_inputs

#: gsplat's default tile edge in pixels (its kernels are tuned for it).
GSPLAT_TILE_SIZE = 16


def rasterize_gsplat(
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
    *,
    tile_size: int = GSPLAT_TILE_SIZE,
) -> RasterOutputs:
    """gsplat rasterization with the contract's inputs and outputs; see ``contract.RasterBackend``.

    Args:
        means ... far_plane: the contract's (shapes and units: ``contract.RasterBackend``).
        tile_size: gsplat's tile edge; only changes which far tails of Gaussians are cut.

    Returns:
        RasterOutputs; ``means2d.grad`` holds dL/d(pixel centre) after backward.
    """
    check_inputs(means, quats, scales, opacities, features, viewmats, Ks)
    if means.device.type != "cuda":
        raise ValueError(f"rasterize_gsplat: tensors are on {means.device}; gsplat needs CUDA (use the torch backend)")
    n_channels = features.shape[-1]
    if backgrounds is not None and tuple(backgrounds.shape) != (viewmats.shape[0], n_channels):
        raise ValueError(
            f"rasterize: backgrounds has shape {tuple(backgrounds.shape)}, expected [C={viewmats.shape[0]}, D={n_channels}]"
        )
    if means.dim() == 3:
        return _rasterize_per_camera(
            means, quats, scales, opacities, features, viewmats, Ks, width, height, backgrounds, near_plane, far_plane,
            tile_size,
        )
    from gsplat.rendering import rasterization

    colours, alphas, meta = rasterization(
        means, quats, scales, opacities, features, viewmats, Ks, width, height,
        near_plane=near_plane, far_plane=far_plane, eps2d=LOW_PASS_EPS, packed=False, tile_size=tile_size,
        backgrounds=backgrounds, render_mode="RGB+ED", rasterize_mode="classic",
    )
    means2d = meta["means2d"]
    if means2d.requires_grad:
        means2d.retain_grad()
    radii = meta["radii"]
    return RasterOutputs(
        render=colours[..., :n_channels], depth=colours[..., n_channels:], alpha=alphas,
        means2d=means2d, radii=radii, visible=radii > 0,
    )


def _rasterize_per_camera(
    means: Float[Tensor, "C N 3"], quats: Float[Tensor, "C N 4"], scales: Float[Tensor, "C N 3"],
    opacities: Float[Tensor, "N"], features: Tensor, viewmats: Float[Tensor, "C 4 4"], Ks: Float[Tensor, "C 3 3"],
    width: int, height: int, backgrounds: Optional[Tensor], near_plane: float, far_plane: float, tile_size: int,
) -> RasterOutputs:
    """Gaussians per camera: gsplat's projection per camera, then ``rasterization``'s binning and
    compositing for all C cameras at once (same arguments as :func:`rasterize_gsplat`)."""
    from gsplat.cuda._wrapper import fully_fused_projection, isect_offset_encode, isect_tiles, rasterize_to_pixels

    n_cams, n_channels = viewmats.shape[0], features.shape[-1]
    parts = [
        fully_fused_projection(
            means[c], None, quats[c], scales[c], viewmats[c : c + 1], Ks[c : c + 1], width, height,
            eps2d=LOW_PASS_EPS, packed=False, near_plane=near_plane, far_plane=far_plane, radius_clip=0.0,
            sparse_grad=False, calc_compensations=False,
        )
        for c in range(n_cams)
    ]
    radii, means2d, depths, conics = (torch.cat([p[i] for p in parts]) for i in range(4))
    colours = features.expand(n_cams, -1, -1) if features.dim() == 2 else features
    colours = torch.cat([colours, depths[..., None]], dim=-1)  # "RGB+ED": the depth as a last channel
    if backgrounds is not None:
        backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(n_cams, 1)], dim=-1)
    tile_width, tile_height = math.ceil(width / float(tile_size)), math.ceil(height / float(tile_size))
    _, isect_ids, flatten_ids = isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height, packed=False,
                                            n_cameras=n_cams)
    isect_offsets = isect_offset_encode(isect_ids, n_cams, tile_width, tile_height)
    if means2d.requires_grad:
        means2d.retain_grad()
    render, alphas = rasterize_to_pixels(
        means2d, conics, colours, opacities.repeat(n_cams, 1), width, height, tile_size, isect_offsets, flatten_ids,
        backgrounds=backgrounds, packed=False,
    )
    return RasterOutputs(
        render=render[..., :n_channels], depth=render[..., n_channels:] / alphas.clamp(min=1e-10), alpha=alphas,
        means2d=means2d, radii=radii, visible=radii > 0,
    )

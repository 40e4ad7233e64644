"""The CUDA backend: gsplat 1.4.0's rasterization behind the one rendering contract.

gsplat is imported inside the function, so CPU-only use never loads (or JIT-compiles) its CUDA
extension. All feature channels (RGB plus extras such as the motion mask) and the expected depth
are rendered in one pass ("RGB+ED").
"""

from __future__ import annotations

from typing import Optional

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
        means: [N, 3] world positions. quats: [N, 4] wxyz. scales: [N, 3] activated, world units.
        opacities: [N] activated. features: [N, D] or [C, N, D], any D.
        viewmats: [C, 4, 4] world-to-camera (OpenCV). Ks: [C, 3, 3] pixel intrinsics.
        width, height: image size in pixels.
        backgrounds: [C, D] colour behind the Gaussians, or None for zeros.
        near_plane, far_plane: depth range in world units.
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

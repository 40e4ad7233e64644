"""How many training views see the static surface behind a pixel.

A pixel whose static surface point lies inside few of the training frames (the floor just below
the first frame's edge, a wall past the path's end) was fitted from few views, so the static
model is poorly constrained there and its residual is reconstruction error more often than
motion. The motion initialisation compares an object's support with the clip's typical support
(``DynamicSeedingConfig.min_view_support``), so a capture whose every pixel is seen by few views
(an orbit) is judged against itself.
"""

from __future__ import annotations

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from edygs_ns.model.dynamic_seeding import backproject

#: at most this many pixels and this many views are used per estimate (a fixed, strided sample)
MAX_PIXELS = 4096
MAX_VIEWS = 64


def _strided(count: int, most: int) -> Tensor:
    """Evenly spaced indices, at most ``most`` of range(count)."""
    return torch.linspace(0, count - 1, min(count, most)).round().long().unique()


def view_support(
    pixels: Bool[Tensor, "N H W"],
    depth: Float[Tensor, "N H W"],
    viewmats: Float[Tensor, "N 4 4"],
    cams_to_world_cv: Float[Tensor, "N 4 4"],
    Ks: Float[Tensor, "N 3 3"],
) -> Float[Tensor, "M"]:
    """Share of the training views (in [0, 1]) whose frame contains the static surface point of
    each of a strided sample of the ``pixels`` (latent, row, column) with a rendered depth.

    Args:
        pixels: which pixels to score; depth: the static render's camera z (world units, 0 where
            nothing was rendered: such pixels are skipped); viewmats: world-to-camera (OpenCV);
            cams_to_world_cv: their inverses; Ks: intrinsics (pixels).

    Returns:
        [M] support of up to ``MAX_PIXELS`` of those pixels, against up to ``MAX_VIEWS`` views;
        empty when none of them has a depth.
    """
    n, height, width = depth.shape
    index = torch.nonzero(pixels & (depth > 0))
    if len(index) == 0:
        return depth.new_zeros(0)
    index = index[_strided(len(index), MAX_PIXELS).to(index.device)]
    points = []
    for k in index[:, 0].unique().tolist():  # back-projected latent by latent
        row, col = index[index[:, 0] == k, 1:].unbind(dim=1)
        points.append(backproject(col, row, depth[k, row, col], Ks[k], cams_to_world_cv[k]))
    world = torch.cat(points)
    views = _strided(n, MAX_VIEWS).to(depth.device)
    seen = torch.einsum("vij,mj->vmi", viewmats[views, :3, :3], world) + viewmats[views, None, :3, 3]
    pix = torch.einsum("vij,vmj->vmi", Ks[views], seen)
    front = seen[..., 2] > 1e-6
    u = pix[..., 0] / pix[..., 2].clamp_min(1e-9)
    v = pix[..., 1] / pix[..., 2].clamp_min(1e-9)
    inside = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return inside.float().mean(dim=0)


def typical_support(
    depth: Float[Tensor, "N H W"],
    viewmats: Float[Tensor, "N 4 4"],
    cams_to_world_cv: Float[Tensor, "N 4 4"],
    Ks: Float[Tensor, "N 3 3"],
) -> float:
    """Median support over all pixels with a rendered depth (1.0 when none has one)."""
    return relative_support(depth > 0, 1.0, depth, viewmats, cams_to_world_cv, Ks)


def relative_support(pixels: Bool[Tensor, "N H W"], typical: float, depth: Float[Tensor, "N H W"],
                     viewmats: Float[Tensor, "N 4 4"], cams_to_world_cv: Float[Tensor, "N 4 4"],
                     Ks: Float[Tensor, "N 3 3"]) -> float:
    """Median view support of ``pixels`` (an object's evidence) over the clip's ``typical`` support
    (``view_support``); 1.0 when none of them has a static depth."""
    values = view_support(pixels, depth, viewmats, cams_to_world_cv, Ks)
    return float(values.median()) / max(typical, 1e-9) if len(values) else 1.0

"""The CPU reference rasteriser: gsplat's tile-based splatting in PyTorch, any device.

Pipeline: project (``projection.py``), cull, bin every visible Gaussian into the 8x8-pixel tiles
it can reach (gsplat's 3-sigma square, cut to where its alpha reaches 1/255), sort the
(tile, depth) pairs with one int64 sort, then composite each tile front to back with gsplat's
alpha rules.

Inside a tile a Gaussian's exponent -sigma + log(o) is a quadratic polynomial of the pixel
position relative to the tile centre; its 6 coefficients are computed per (Gaussian, tile)
intersection with ordinary autograd ops. The compositing is a hand-written
``torch.autograd.Function`` over blocks of tiles laid out [tiles, pixels, K] (K: intersections
of the tile, padded to the block's largest tile): the exponents of a block are one matmul
``[P, 6] @ [tiles, 6, K]``, the colours one bmm, and its backward returns gradients per
intersection. Work and memory follow the pixels each Gaussian covers; every block holds about
``BLOCK_ELEMENTS`` elements.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Tuple

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor

from edygs_ns.render.contract import (
    ALPHA_MAX,
    ALPHA_MIN,
    DEFAULT_FAR,
    DEFAULT_NEAR,
    TRANSMITTANCE_MIN,
    RasterOutputs,
    check_inputs,
)
from edygs_ns.render.projection import project_gaussians

#: tile edge in pixels (8x8 measured faster than 16x16 and on par with 4x4 on CPU).
TILE_SIZE = 8
#: target number of [tile, pixel, Gaussian] elements per compositing block (2 MiB in float32).
BLOCK_ELEMENTS = 1 << 19
#: forward keeps the weights for backward while they fit in this many bytes; above it the
#: backward recomputes them block by block.
SAVE_BUDGET_BYTES = 256 << 20
#: exponents are clamped here before exp (exp(-20) < ALPHA_MIN; CPU exp is slow far below).
MAX_EXPONENT = 20.0
#: opacities are clamped to this before the log (only matters for exactly-zero opacities).
MIN_OPACITY = 1e-30
#: constant exponent of the padding intersection: its alpha underflows to 0 everywhere.
PAD_EXPONENT = -1e4
#: expected depth divides by alpha clamped to this (gsplat's value).
MIN_ALPHA_FOR_DEPTH = 1e-10
#: exponent coefficients per intersection: 1, x, y, x^2, y^2, xy of the tile-local pixel position.
N_COEFFS = 6
#: offset of a pixel centre from its corner (gsplat samples at j + 0.5).
PIXEL_CENTRE = 0.5
#: slack on the exponent when dropping (Gaussian, tile) pairs whose alpha is below ALPHA_MIN.
CULL_MARGIN = 1e-3
LOG2_E = 1.0 / math.log(2.0)


@dataclass
class TileBins:
    """Visible Gaussians sorted by (camera, tile, depth): M (Gaussian, tile) intersections.

    Attributes:
        flat_ids: [M] int64 index c * N + n of the Gaussian of each intersection.
        tile_ids: [M] int64 tile (c * T + row * tiles_x + column) of each intersection.
        tile_starts: [C * T] int64 first intersection of each tile.
        tile_counts: [C * T] int64 number of intersections of each tile.
        tiles_x, tiles_y: tiles per image row / column (T = tiles_x * tiles_y).
    """

    flat_ids: Tensor
    tile_ids: Tensor
    tile_starts: Tensor
    tile_counts: Tensor
    tiles_x: int
    tiles_y: int


@dataclass
class _Block:
    """Tiles composited together; ``slots`` [t, K] index the intersection table (pad = last row)."""

    tiles: Tensor
    slots: Tensor
    can_clamp: bool  # some Gaussian of the block has opacity above ALPHA_MAX


def bin_gaussians(
    means2d: Tensor,
    radii: Tensor,
    depths: Tensor,
    width: int,
    height: int,
    tile_size: int = TILE_SIZE,
    conics: Optional[Tensor] = None,
    opacities: Optional[Tensor] = None,
) -> TileBins:
    """Bin every visible Gaussian into the tiles its radius square touches (gsplat's isect_tiles).

    With ``conics`` and ``opacities`` the tile range is also cut to the tiles with a pixel centre in
    the bounding box of the ellipse where the Gaussian's alpha reaches ALPHA_MIN. The dropped
    (Gaussian, tile) pairs have alpha below ALPHA_MIN at every pixel of the tile, which gsplat
    skips pixel by pixel, so the image is the same with about a third less work.

    Args:
        means2d: [C, N, 2] pixel centres. radii: [C, N] int, 0 = culled. depths: [C, N].
        width, height: image size in pixels. tile_size: tile edge in pixels.
        conics: [C, N, 3] inverse 2D covariances. opacities: [N] activated opacities.
    """
    n_cams, n = radii.shape
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    n_tiles = tiles_x * tiles_y
    device = radii.device
    with torch.no_grad():
        flat = torch.nonzero(radii.reshape(-1) > 0).squeeze(1)  # [V]
        centre = means2d.detach().reshape(-1, 2).index_select(0, flat)
        rad = radii.reshape(-1).index_select(0, flat).to(centre.dtype)
        x0 = torch.floor((centre[:, 0] - rad) / tile_size).clamp(0, tiles_x).long()
        x1 = torch.ceil((centre[:, 0] + rad) / tile_size).clamp(0, tiles_x).long()
        y0 = torch.floor((centre[:, 1] - rad) / tile_size).clamp(0, tiles_y).long()
        y1 = torch.ceil((centre[:, 1] + rad) / tile_size).clamp(0, tiles_y).long()
        if conics is not None and opacities is not None:
            # tiles with a pixel centre inside the bounding box of {alpha >= ALPHA_MIN}
            level = torch.log(opacities.detach().to(centre.dtype).clamp(min=MIN_OPACITY) / ALPHA_MIN)[flat % n]
            conic_v = conics.detach().reshape(-1, 3).index_select(0, flat)
            det = conic_v[:, 0] * conic_v[:, 2] - conic_v[:, 1] ** 2
            reach = 2.0 * (level + CULL_MARGIN).clamp(min=0.0) / det
            half = torch.stack([conic_v[:, 2], conic_v[:, 0]], 1).mul(reach[:, None]).sqrt()  # [V, 2] pixels
            first_px = torch.ceil(centre - half - PIXEL_CENTRE)
            last_px = torch.floor(centre + half - PIXEL_CENTRE)
            first_tile = torch.div(first_px, tile_size, rounding_mode="floor").long()
            last_tile = torch.div(last_px, tile_size, rounding_mode="floor").long() + 1
            x0, y0 = torch.maximum(x0, first_tile[:, 0]), torch.maximum(y0, first_tile[:, 1])
            x1 = torch.maximum(torch.minimum(x1, last_tile[:, 0]), x0)
            y1 = torch.maximum(torch.minimum(y1, last_tile[:, 1]), y0)
        nx = x1 - x0
        counts = nx * (y1 - y0)
        # depth rank of every visible Gaussian: exact ordering in any dtype, fits in 32 bits
        rank = torch.empty_like(flat)
        rank[torch.argsort(depths.detach().reshape(-1).index_select(0, flat))] = torch.arange(len(flat), device=device)
        first = torch.cumsum(counts, 0) - counts
        base = torch.div(flat, n, rounding_mode="floor") * n_tiles + y0 * tiles_x + x0  # tile of the first corner
        owner = torch.repeat_interleave(torch.arange(len(flat), device=device), counts)  # [M]
        per_owner = torch.stack([base, nx, first, rank], 1).index_select(0, owner)  # one gather
        local = torch.arange(len(owner), device=device) - per_owner[:, 2]
        dy = torch.div(local, per_owner[:, 1], rounding_mode="floor")
        dx = local - dy * per_owner[:, 1]
        tile = per_owner[:, 0] + dy * tiles_x + dx
        keys, order = torch.sort((tile << 32) | per_owner[:, 3])
        tile_counts = torch.bincount(keys >> 32, minlength=n_cams * n_tiles)
        tile_starts = torch.cumsum(tile_counts, 0) - tile_counts
    return TileBins(
        flat.index_select(0, owner.index_select(0, order)), keys >> 32, tile_starts, tile_counts, tiles_x, tiles_y
    )


def _plan_blocks(bins: TileBins, tile_size: int, opacity_of_isect: Tensor) -> List[_Block]:
    """Group non-empty tiles (largest first) into blocks of about BLOCK_ELEMENTS elements.

    Args:
        opacity_of_isect: [M + 1] opacity of each intersection's Gaussian (0 for the pad row).
    """
    pixels = tile_size * tile_size
    counts = bins.tile_counts
    pad = len(bins.flat_ids)
    order = torch.argsort(counts, descending=True)
    order = order[: int((counts > 0).sum())]
    sorted_counts = counts[order].tolist()
    blocks: List[_Block] = []
    start = 0
    while start < len(sorted_counts):
        k = sorted_counts[start]
        stop = min(len(sorted_counts), start + max(1, BLOCK_ELEMENTS // (pixels * k)))
        tiles = order[start:stop]
        slot = torch.arange(k, device=counts.device)
        slots = torch.where(slot < counts[tiles, None], bins.tile_starts[tiles, None] + slot, pad)
        can_clamp = bool(opacity_of_isect[slots].max() > ALPHA_MAX)
        blocks.append(_Block(tiles, slots, can_clamp))
        start = stop
    return blocks


def _pixel_basis(tile_size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """[P, 6] monomials (1, x, y, x^2, y^2, xy) of pixel centres relative to the tile centre."""
    offs = torch.arange(tile_size, dtype=dtype, device=device) + PIXEL_CENTRE - tile_size / 2.0
    py, px = torch.meshgrid(offs, offs, indexing="ij")
    px, py = px.reshape(-1), py.reshape(-1)
    return torch.stack([torch.ones_like(px), px, py, px * px, py * py, px * py], dim=-1)


def exponent_coefficients(
    means2d: Tensor, conics: Tensor, log_opacity: Tensor, centres: Tensor
) -> Tensor:
    """Coefficients of log(alpha) = log(o) - sigma as a polynomial of the pixel offset from a centre.

    Args:
        means2d: [M, 2] Gaussian centres. conics: [M, 3] (a, b, c). log_opacity: [M].
        centres: [M, 2] tile centres, pixels.

    Returns:
        [M, 6] coefficients of (1, x, y, x^2, y^2, xy).
    """
    mx, my = (means2d - centres).unbind(-1)
    ca, cb, cc = conics.unbind(-1)
    return torch.stack(
        [
            log_opacity - 0.5 * ca * mx * mx - 0.5 * cc * my * my - cb * mx * my,
            ca * mx + cb * my,
            cc * my + cb * mx,
            -0.5 * ca,
            -0.5 * cc,
            -cb,
        ],
        dim=-1,
    )


def _block_forward(basis2: Tensor, rows: Tensor, can_clamp: bool, need_grad: bool) -> Tuple[Tensor, Tensor, Optional[Tensor]]:
    """Compositing weights of one block, gsplat's rules.

    Args:
        basis2: [P, 6] pixel monomials times log2(e) (exp2 is about twice as fast as exp on CPU).
        rows: [t, K, 6 + F] gathered intersection rows (coefficients, features).

    Returns:
        weights w = alpha * T_before [t, P, K]; alpha / (1 - alpha) [t, P, K] (meaningful only
        when need_grad); for blocks where alpha can clamp, the [t, P, K] mask of unclamped alphas.
    """
    alpha = torch.matmul(basis2, rows[..., :N_COEFFS].transpose(1, 2))  # log2(alpha)
    F.threshold_(alpha, -MAX_EXPONENT * LOG2_E, -MAX_EXPONENT * LOG2_E)  # clamp from below
    alpha.exp2_()
    F.threshold_(alpha, ALPHA_MIN, 0.0)  # gsplat skips alpha < 1/255
    unclamped = None
    if can_clamp:
        unclamped = alpha < ALPHA_MAX if need_grad else None
        F.hardtanh_(alpha, 0.0, ALPHA_MAX)
    n_tiles, n_pix, k = alpha.shape
    trans = alpha.new_empty(n_tiles, n_pix, k + 1)  # [..., j] = transmittance before Gaussian j
    trans[..., 0] = 1.0
    torch.neg(alpha, out=trans[..., 1:]).add_(1.0)
    torch.cumprod(trans, -1, out=trans)
    weights = alpha * trans[..., :-1]
    if float(trans[..., -1].min()) <= TRANSMITTANCE_MIN:
        # a pixel stops before the Gaussian that would take its transmittance to <= T_min
        keep = F.threshold_(trans, TRANSMITTANCE_MIN, 0.0).sign_()[..., 1:]  # reuses the buffer
        weights.mul_(keep)
        alpha.mul_(keep)
    if need_grad:
        alpha.div_(torch.neg(alpha, out=trans[..., 1:]).add_(1.0))
    return weights, alpha, unclamped


class _Composite(torch.autograd.Function):
    """Front-to-back compositing of tile blocks from the [M + 1, 6 + F] intersection table."""

    @staticmethod
    def forward(ctx, table: Tensor, blocks: List[_Block], n_tiles: int, tile_size: int) -> Tensor:  # type: ignore[override]
        basis2 = _pixel_basis(tile_size, table.dtype, table.device) * LOG2_E
        n_feat = table.shape[1] - N_COEFFS
        out = table.new_zeros(n_tiles, n_feat, basis2.shape[0])  # channels before pixels: fast bmm
        need_grad = bool(ctx.needs_input_grad[0])
        n_elements = sum(b.slots.numel() for b in blocks) * basis2.shape[0]
        save = need_grad and 2 * n_elements * table.element_size() <= SAVE_BUDGET_BYTES
        saved: List[Tuple[Tensor, Tensor, Optional[Tensor]]] = []
        for block in blocks:
            rows = _gather_rows(table, block.slots)
            weights, ratio, unclamped = _block_forward(basis2, rows, block.can_clamp, need_grad)
            out.index_copy_(0, block.tiles, torch.bmm(rows[..., N_COEFFS:].transpose(1, 2), weights.transpose(1, 2)))
            if save:
                saved.append((weights, ratio, unclamped))
        ctx.blocks, ctx.saved, ctx.tile_size = blocks, saved, tile_size
        ctx.save_for_backward(table)
        return out.transpose(1, 2)

    @staticmethod
    def backward(ctx, grad_out: Tensor):  # type: ignore[override]
        (table,) = ctx.saved_tensors
        basis = _pixel_basis(ctx.tile_size, table.dtype, table.device)
        grad_table = table.new_zeros(table.shape[1], table.shape[0])  # [columns, rows]
        grad_out = grad_out.contiguous()
        for i, block in enumerate(ctx.blocks):
            rows = _gather_rows(table, block.slots)
            if ctx.saved:
                weights, ratio, unclamped = ctx.saved[i]
            else:
                weights, ratio, unclamped = _block_forward(basis * LOG2_E, rows, block.can_clamp, True)
            g_pix = grad_out.index_select(0, block.tiles)  # [t, P, F]
            # with h_k = dL/dC . f_k:  dL/dalpha_k = T_k h_k - (sum_{j>k} w_j h_j) / (1 - alpha_k);
            # dalpha/dlog(alpha) = alpha, so dL/dlog(alpha_k) = w_k h_k - ratio_k * sum_{j>k} w_j h_j
            g = torch.bmm(g_pix, rows[..., N_COEFFS:].transpose(1, 2)).mul_(weights)  # [t, P, K]
            later = torch.cumsum(g, -1)
            later.sub_(later[..., -1:].clone()).mul_(ratio)
            g.add_(later)
            if unclamped is not None:
                g.mul_(unclamped)
            g_rows = torch.cat([torch.matmul(basis.t(), g), torch.bmm(g_pix.transpose(1, 2), weights)], 1)  # [t, 6+F, K]
            grad_table.index_copy_(1, block.slots.reshape(-1), g_rows.transpose(0, 1).reshape(table.shape[1], -1))
        ctx.saved = None
        grad_table[:, -1] = 0.0  # the pad row (several slots wrote to it)
        return grad_table.t(), None, None, None


def _gather_rows(table: Tensor, slots: Tensor) -> Tensor:
    """[t, K, columns] rows of the table (index_select is faster than advanced indexing on CPU)."""
    return table.index_select(0, slots.reshape(-1)).view(*slots.shape, table.shape[1])


def _tiles_to_image(tiled: Tensor, n_cams: int, bins: TileBins, width: int, height: int, tile_size: int) -> Tensor:
    """[C*T, P, F] tile layout -> [C, H, W, F] image."""
    n_feat = tiled.shape[-1]
    img = tiled.reshape(n_cams, bins.tiles_y, bins.tiles_x, tile_size, tile_size, n_feat)
    img = img.permute(0, 1, 3, 2, 4, 5).reshape(n_cams, bins.tiles_y * tile_size, bins.tiles_x * tile_size, n_feat)
    return img[:, :height, :width]


def rasterize_torch(
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
    tile_size: int = TILE_SIZE,
) -> RasterOutputs:
    """Differentiable tile rasteriser with gsplat's rules; see ``contract.RasterBackend``.

    Args:
        means: [N, 3] world positions. quats: [N, 4] wxyz. scales: [N, 3] activated, world units.
        opacities: [N] activated. features: [N, D] or [C, N, D], any D.
        viewmats: [C, 4, 4] world-to-camera (OpenCV). Ks: [C, 3, 3] pixel intrinsics.
        width, height: image size in pixels.
        backgrounds: [C, D] colour behind the Gaussians, or None for zeros.
        near_plane, far_plane: depth range in world units.
        tile_size: tile edge in pixels; only changes which far tails of Gaussians are cut.

    Returns:
        RasterOutputs; gradients reach means, quats, scales, opacities, features and viewmats,
        and ``means2d.grad`` holds dL/d(pixel centre) after backward.
    """
    check_inputs(means, quats, scales, opacities, features, viewmats, Ks)
    n_cams, n = viewmats.shape[0], means.shape[0]
    n_channels = features.shape[-1]
    if backgrounds is not None and tuple(backgrounds.shape) != (n_cams, n_channels):
        raise ValueError(
            f"rasterize: backgrounds has shape {tuple(backgrounds.shape)}, expected [C={n_cams}, D={n_channels}]"
        )
    proj = project_gaussians(means, quats, scales, viewmats, Ks, width, height, near_plane, far_plane)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    bins = bin_gaussians(means2d, proj.radii, proj.depths, width, height, tile_size, proj.conics, opacities)

    # one row per intersection: exponent coefficients, then features, depth and 1 (for alpha)
    flat, gauss = bins.flat_ids, bins.flat_ids % n
    in_image = bins.tile_ids % (bins.tiles_x * bins.tiles_y)
    corner = torch.stack([in_image % bins.tiles_x, torch.div(in_image, bins.tiles_x, rounding_mode="floor")], -1)
    centres = (corner * tile_size).to(means2d.dtype) + tile_size / 2.0
    feats = features.reshape(-1, n_channels) if features.dim() == 3 else features
    coeffs = exponent_coefficients(
        means2d.reshape(-1, 2).index_select(0, flat),
        proj.conics.reshape(-1, 3).index_select(0, flat),
        torch.log(opacities.clamp(min=MIN_OPACITY)).index_select(0, gauss),
        centres,
    )
    table = torch.cat(
        [
            coeffs,
            feats.index_select(0, flat if features.dim() == 3 else gauss),
            proj.depths.reshape(-1, 1).index_select(0, flat),
            torch.ones_like(coeffs[:, :1]),
        ],
        dim=-1,
    )
    pad = table.new_zeros(1, table.shape[1])
    pad[0, 0] = PAD_EXPONENT
    table = torch.cat([table, pad], dim=0)

    opacity_of_isect = torch.cat([opacities.detach().index_select(0, gauss), opacities.new_zeros(1)])
    blocks = _plan_blocks(bins, tile_size, opacity_of_isect)
    tiled = _Composite.apply(table, blocks, n_cams * bins.tiles_x * bins.tiles_y, tile_size)
    image = _tiles_to_image(tiled, n_cams, bins, width, height, tile_size)
    colour, depth_sum, alpha = image[..., :n_channels], image[..., n_channels : n_channels + 1], image[..., -1:]
    if backgrounds is not None:
        colour = colour + (1.0 - alpha) * backgrounds[:, None, None, :]
    depth = depth_sum / alpha.clamp(min=MIN_ALPHA_FOR_DEPTH)
    return RasterOutputs(
        render=colour, depth=depth, alpha=alpha, means2d=means2d, radii=proj.radii, visible=proj.radii > 0
    )

"""The CPU reference rasteriser: gsplat's tile-based splatting in PyTorch, any device.

Pipeline: project (``projection.py``, hand-written backward), cull, bin every visible Gaussian
into the 8x8-pixel tiles it can reach (gsplat's 3-sigma square, cut to where its alpha reaches
1/255), sort the (tile, depth) pairs with one int64 sort, then composite front to back with
gsplat's alpha rules.

The 8x8 tiles decide *which* Gaussians may touch a pixel (gsplat's rule, so the image does not
change); the work is done on 4x4-pixel cells, the tile quadrants: a (Gaussian, tile) pair is
composited only in the quadrants that hold a pixel centre inside its alpha >= 1/255 ellipse
(its box, then the ellipse's exact extent per row of cells). For the ~1 pixel Gaussians of a
dense scene this leaves about half the elements of whole 8x8 tiles (47% for 20k Gaussians on
128x128, 51% for 100k on 400x400), and about half of those have alpha >= 1/255. A tile whose
intersections mostly reach all four quadrants (large Gaussians) is composited whole instead.

Inside a tile a Gaussian's exponent -sigma + log(o) is a quadratic polynomial of the pixel
position relative to the tile centre. ``_Rasterize`` (one autograd Function) writes its 6
coefficients, the features and the depth into a table with one row per intersection, then
composites blocks of cells laid out [P, t, K] (pixels, cells, intersections of a cell padded to
the block's largest): the exponents of a block are one matmul per quadrant
``[P, 6] @ [6, t K]``, the scans run along the contiguous last axis, the colours are one bmm. Its
backward returns per-intersection gradients, turns them into gradients of the per-Gaussian
inputs in closed form and sums them with one index_add. Every block holds about
``BLOCK_ELEMENTS`` elements; the large buffers are reused between calls (``_take``).

CPU rules of thumb behind the code (measured on a 2-core AMD EPYC VM, torch 2.14): elementwise
ops on [N] rows are 10-50x faster than broadcasts with a tiny inner dimension ([N, 2], [N, 3, 3]);
int64 division / modulo are ~15x slower than float32; autograd costs ~30 us per op; fresh memory
costs page faults on every call.
"""

from __future__ import annotations

import functools
import math
import sys
import threading
import weakref
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
from edygs_ns.render.projection import project_gaussians, project_per_camera

#: tile edge in pixels: decides which Gaussians may reach a pixel (gsplat's 3-sigma square rule).
TILE_SIZE = 8
#: target number of [cell, pixel, Gaussian] elements per compositing block (2 MiB in float32).
BLOCK_ELEMENTS = 1 << 19
#: a slot (a table row gathered in forward and backward, scattered in backward) costs about as
#: much as this many [pixel, intersection] elements; decides whole tiles versus quadrant cells.
SLOT_PIXELS = 8
#: forward keeps the weights for backward while they fit in this many bytes; above it the
#: backward recomputes them block by block.
SAVE_BUDGET_BYTES = 256 << 20
#: spare compositing buffers kept per thread between calls (see ``_take``).
SPARE_BUFFERS = 4
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
        quadrants: [M] uint8 bit mask of the tile quadrants (bit 2 * row + column) that hold a
            pixel centre where the Gaussian's alpha can reach ALPHA_MIN; None when the bins were
            made without conics and opacities (every pixel of the tile may be reached).
    """

    flat_ids: Tensor
    tile_ids: Tensor
    tile_starts: Tensor
    tile_counts: Tensor
    tiles_x: int
    tiles_y: int
    quadrants: Optional[Tensor] = None


@dataclass
class _Cells:
    """What each compositing unit sees, depth-sorted: whole tiles, or the cells (quadrants) of a tile.

    A tile is composited whole when most of its intersections reach all its quadrants (splitting
    would add gathered rows without dropping pixels), else per quadrant. Cell
    (c * T + tile) * s^2 + row * s + column (s = cells per tile edge, 1 or 2); the slots of a cell
    are contiguous from ``starts``; ``rows`` [S + 1] are intersection (table row) indices, the last
    one M, the pad row of the table. A whole tile's intersections are its table rows
    ``tile_starts[tile] + k`` (the table is sorted by tile).
    """

    rows: Tensor
    starts: Tensor
    counts: Tensor  # [C * T * s^2], 0 for the cells of whole tiles
    tile_starts: Tensor
    tile_counts: Tensor  # [C * T], 0 for split tiles
    per_side: int
    size: int


@dataclass
class _Block:
    """Cells composited together; ``slots`` [t, K] index the intersection table (pad = last row)."""

    cells: Tensor  # cell ids, or tile ids for a block of whole tiles
    slots: Tensor
    can_clamp: bool  # some Gaussian of the block has opacity above ALPHA_MAX
    # (quadrant, first, stop): cells [first, stop) are that cell of their tile; quadrant -1: whole tiles
    quadrants: List[Tuple[int, int, int]]
    pixels: int


#: bits of the sort key below the tile id: 31 for the depth (or its rank), 4 for the quadrant mask.
_DEPTH_SHIFT = 4
_TILE_SHIFT = 35


def _depth_keys(depths: Tensor) -> Tensor:
    """[V] int64 keys in depth order, < 2^31: the float32 bit pattern of positive depths (monotonic),
    else the exact rank (float64, or depths <= 0 with a near plane <= 0)."""
    if depths.dtype == torch.float32 and len(depths) and bool(depths.min() > 0):
        return depths.view(torch.int32).long()
    rank = torch.empty(len(depths), dtype=torch.long, device=depths.device)
    rank[torch.argsort(depths)] = torch.arange(len(depths), device=depths.device)
    return rank


#: bands of cells (half-tile rows) per Gaussian whose pixel columns are cut to the ellipse: as
#: many as BAND_QUANTILE of the Gaussians need (at least 4), within BAND_ELEMENTS [bands, V] elements
BAND_QUANTILE = 0.95
BAND_ELEMENTS = 1 << 19
_MIN_BANDS = 4
#: slack in pixels on the ellipse's band extents (covers float rounding; only adds work)
_BAND_SLACK = 0.01


def _band_columns(
    cx: Tensor, cy: Tensor, ca: Tensor, cb: Tensor, cc: Tensor, r2: Tensor, half_x: Tensor, half_y: Tensor,
    fx: Tensor, fy: Tensor, lx: Tensor, ly: Tensor, band: int,
) -> Tuple[Tensor, Tensor, Tensor, int]:
    """First / last pixel column the ellipse (d^T Q d <= r2) reaches in each of its first B
    bands of ``band`` pixel rows, starting at the band of its first pixel row.

    In a band [y0, y1] the ellipse's x extent is [x_left(clamp(y_L)), x_right(clamp(y_R))]:
    x_left is convex in y with its minimum at the leftmost point y_L, x_right concave. A band it
    misses gets an empty range. Entry B is the whole box (for taller Gaussians).

    Returns:
        [(B + 1) * V] float32 first and last columns (band-major), [V] the first band, and B.
    """
    f32 = torch.float32
    first_band = torch.floor(fy / band)
    # enough bands for BAND_QUANTILE of the Gaussians (taller ones fall back to their box)
    heights = (torch.floor(ly / band) - first_band).clamp_(0, 4095).long() + 1
    cover = torch.cumsum(torch.bincount(heights), 0) if len(fy) else heights
    n_bands = int((cover < BAND_QUANTILE * len(fy)).sum()) + 1
    n_bands = max(1, min(len(cover) - 1, max(_MIN_BANDS, n_bands), BAND_ELEMENTS // max(len(fy), 1)))
    # [B, V] rows: bands lead, Gaussians contiguous (broadcasts along V stay fast)
    offsets = torch.arange(n_bands, dtype=cy.dtype, device=cy.device)[:, None] * band
    top = (first_band.to(cy.dtype) * band - cy + (PIXEL_CENTRE - _BAND_SLACK)) + offsets
    lo = torch.maximum(top, -half_y)
    hi = torch.minimum(top + (band - 1 + 2 * _BAND_SLACK), half_y)
    det = ca * cc - cb * cb
    dy_left = cb * half_x / cc  # y offset of the leftmost point (the rightmost is at -dy_left)
    a_r2 = ca * r2
    ends = []
    for dy0, sign in ((dy_left, -1.0), (-dy_left, 1.0)):
        dy = torch.clamp(dy0, min=lo, max=hi)
        width = torch.addcmul(a_r2, det, dy * dy, value=-1.0).clamp_(min=0.0).sqrt_()
        ends.append(width.mul_(sign).addcmul_(cb, dy, value=-1.0).div_(ca).add_(cx))
    missed = (lo > hi).to(f32).mul_(4.0 * 2**20)
    first = torch.maximum(ends[0].sub_(PIXEL_CENTRE + _BAND_SLACK).ceil_().to(f32), fx).add_(missed)
    last = torch.minimum(ends[1].sub_(PIXEL_CENTRE - _BAND_SLACK).floor_().to(f32), lx).sub_(missed)
    first, last = torch.cat([first.view(-1), fx]), torch.cat([last.view(-1), lx])
    return first, last, first_band, n_bands


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
    skips pixel by pixel, so the image is the same with about a third less work. The box and
    the ellipse's extent per half-tile row give the quadrants of each tile the Gaussian can
    reach (``TileBins.quadrants``; the same argument: the others get alpha < ALPHA_MIN).

    Index arithmetic runs in float32 on [V] / [M] rows (exact below 2^24): on CPU int64 division
    and modulo are ~15x slower, and [V, 2] broadcasts ~10x slower than 1-D ops.

    Args:
        means2d: [C, N, 2] pixel centres. radii: [C, N] int, 0 = culled. depths: [C, N].
        width, height: image size in pixels. tile_size: tile edge in pixels.
        conics: [C, N, 3] inverse 2D covariances. opacities: [N] activated opacities.
    """
    n_cams, n = radii.shape
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    n_tiles = tiles_x * tiles_y
    if n_cams * n_tiles >= 1 << (63 - _TILE_SHIFT):
        raise ValueError(f"rasterize: {n_cams} cameras x {n_tiles} tiles do not fit the sort key")
    device = radii.device
    f32 = torch.float32
    half_tile = tile_size // 2 if tile_size % 2 == 0 else 0
    with torch.no_grad():
        # tile and pixel ranges of each visible Gaussian in the input precision (the rule), then
        # as small integers in float32
        flat = torch.nonzero(radii.reshape(-1) > 0).squeeze(1)  # [V]
        centre = means2d.detach().reshape(-1, 2).index_select(0, flat)
        cx, cy = centre[:, 0].contiguous(), centre[:, 1].contiguous()
        rad = radii.reshape(-1).index_select(0, flat).to(centre.dtype)
        x0 = torch.floor((cx - rad) / tile_size).clamp_(0, tiles_x).to(f32)
        x1 = torch.ceil((cx + rad) / tile_size).clamp_(0, tiles_x).to(f32)
        y0 = torch.floor((cy - rad) / tile_size).clamp_(0, tiles_y).to(f32)
        y1 = torch.ceil((cy + rad) / tile_size).clamp_(0, tiles_y).to(f32)
        box = None
        if conics is not None and opacities is not None:
            # tiles with a pixel centre inside the bounding box of {alpha >= ALPHA_MIN}
            op = opacities.detach().to(centre.dtype).clamp(min=MIN_OPACITY)
            level = torch.log(op / ALPHA_MIN).index_select(0, flat % n)
            conic_v = conics.detach().reshape(-1, 3).index_select(0, flat)
            ca, cb, cc = conic_v[:, 0], conic_v[:, 1], conic_v[:, 2]
            r2 = 2.0 * (level + CULL_MARGIN).clamp_(min=0.0)  # the ellipse d^T Q d <= r2
            reach = r2 / (ca * cc - cb * cb)
            half_x, half_y = (cc * reach).sqrt_(), (ca * reach).sqrt_()
            # first / last pixel index with a centre in the box (clamped just outside the image)
            limit = float(max(width, height) + tile_size)
            fx = torch.ceil(cx - half_x - PIXEL_CENTRE).clamp_(-limit, limit).to(f32)
            lx = torch.floor(cx + half_x - PIXEL_CENTRE).clamp_(-limit, limit).to(f32)
            fy = torch.ceil(cy - half_y - PIXEL_CENTRE).clamp_(-limit, limit).to(f32)
            ly = torch.floor(cy + half_y - PIXEL_CENTRE).clamp_(-limit, limit).to(f32)
            x0 = torch.maximum(x0, torch.floor(fx / tile_size))
            y0 = torch.maximum(y0, torch.floor(fy / tile_size))
            x1 = torch.maximum(torch.minimum(x1, torch.floor(lx / tile_size) + 1), x0)
            y1 = torch.maximum(torch.minimum(y1, torch.floor(ly / tile_size) + 1), y0)
            box = [fx, fy, lx, ly]
            if half_tile:
                band_lo, band_hi, first_band, n_bands = _band_columns(
                    cx, cy, ca, cb, cc, r2, half_x, half_y, fx, fy, lx, ly, half_tile
                )
        nx, ny = x1 - x0, y1 - y0
        counts = (nx * ny).long()
        quadrant_cut = box is not None and half_tile > 0
        if quadrant_cut:
            # which half of its first / last tile column (row) the box cannot reach: bit 0 the
            # left half of the first column, 1 the right half of the last, 2 / 3 the same for rows
            fx, fy, lx, ly = box
            u8 = torch.uint8
            edges = (
                (fx >= x0 * tile_size + half_tile).to(u8)
                | ((lx < (x1 - 1) * tile_size + half_tile).to(u8) << 1)
                | ((fy >= y0 * tile_size + half_tile).to(u8) << 2)
                | ((ly < (y1 - 1) * tile_size + half_tile).to(u8) << 3)
            )
        # the sort key of each visible Gaussian without its tile: camera's first tile, depth
        cam_tile = torch.div(flat, n, rounding_mode="floor") * n_tiles if n_cams > 1 else torch.zeros_like(flat)
        depth_key = _depth_keys(depths.detach().reshape(-1).index_select(0, flat))
        vkey = (cam_tile << _TILE_SHIFT) | (depth_key << _DEPTH_SHIFT)
        # per intersection: one 1-D gather per quantity (fastest on CPU), index math in float32
        owner = torch.repeat_interleave(torch.arange(len(flat), device=device), counts)  # [M]
        first = torch.cumsum(counts, 0) - counts
        if len(owner) < 1 << 24:
            local = torch.arange(len(owner), device=device, dtype=f32) - first.to(f32).index_select(0, owner)
        else:
            local = (torch.arange(len(owner), device=device) - first.index_select(0, owner)).to(f32)
        onx = nx.index_select(0, owner)
        dy = torch.floor((local + 0.5) / onx)
        dx = local - dy * onx
        col, row = x0.index_select(0, owner) + dx, y0.index_select(0, owner) + dy  # tile of each intersection
        key = ((row * tiles_x + col).long() << _TILE_SHIFT).add_(vkey.index_select(0, owner))
        if quadrant_cut:
            # quadrants of the tile with a pixel centre in the box (the box always reaches the tile)
            code = edges.index_select(0, owner)
            left = ~((dx == 0) & (code & 1).view(torch.bool))
            right = ~((dx == onx - 1) & ((code >> 1) & 1).view(torch.bool))
            top = ~((dy == 0) & ((code >> 2) & 1).view(torch.bool))
            bottom = ~((dy == ny.index_select(0, owner) - 1) & ((code >> 3) & 1).view(torch.bool))
            # and the ellipse itself: its pixel columns in the tile's top / bottom band of cells
            rel = 2.0 * row - first_band.index_select(0, owner)  # band of the tile's top half
            col_first = col * tile_size
            small = len(band_lo) < 1 << 24  # float32 index math is exact (and ~10x faster than int64)
            owner_f = owner.to(f32) if small else owner
            for half in (0, 1):
                band_of = (rel + half).clamp_(0, n_bands)
                at = (band_of * len(flat) + owner_f).to(torch.int32) if small else band_of.long() * len(flat) + owner
                lo, hi = band_lo.index_select(0, at), band_hi.index_select(0, at)
                reach_l = (lo <= col_first + (half_tile - 1)) & (hi >= col_first)
                reach_r = (lo <= col_first + (tile_size - 1)) & (hi >= col_first + half_tile)
                if half == 0:
                    top_l, top_r = top & left & reach_l, top & right & reach_r
                else:
                    bot_l, bot_r = bottom & left & reach_l, bottom & right & reach_r
            quad = top_l.to(u8) | (top_r.to(u8) << 1) | (bot_l.to(u8) << 2) | (bot_r.to(u8) << 3)
            key |= quad.long()
        keys, order = torch.sort(key)
        tile_ids = keys >> _TILE_SHIFT
        tile_counts = torch.bincount(tile_ids, minlength=n_cams * n_tiles)
        tile_starts = torch.cumsum(tile_counts, 0) - tile_counts
        quadrants = None
        if quadrant_cut:  # the key's low 4 bits
            low_byte = keys.view(torch.uint8)[:: 8] if sys.byteorder == "little" else keys.to(torch.uint8)
            quadrants = low_byte & ((1 << _DEPTH_SHIFT) - 1)
    flat_ids = flat.index_select(0, owner.index_select(0, order))
    return TileBins(flat_ids, tile_ids, tile_starts, tile_counts, tiles_x, tiles_y, quadrants)


def _split_cells(bins: TileBins, tile_size: int) -> _Cells:
    """Choose whole tiles or quadrant cells per tile; list the intersections of every quadrant cell."""
    device = bins.flat_ids.device
    n_isect, n_tiles = len(bins.flat_ids), len(bins.tile_counts)
    pad = torch.full((1,), n_isect, dtype=torch.long, device=device)
    if tile_size % 2 != 0 or bins.quadrants is None:  # every tile whole
        side = 2 if tile_size % 2 == 0 else 1
        empty = bins.tile_counts.new_zeros(n_tiles * side * side)
        return _Cells(pad, empty, empty, bins.tile_starts, bins.tile_counts, side, tile_size // side)
    with torch.no_grad():
        rows, counts = [], []
        for quadrant in range(4):  # [M] uint8 bit tests: 8x cheaper than int64
            # depth order inside a tile is kept: nonzero lists the intersections in sorted order
            hit = torch.nonzero(((bins.quadrants >> quadrant) & 1).view(torch.bool)).squeeze(1)
            rows.append(hit)
            counts.append(torch.bincount(bins.tile_ids.index_select(0, hit), minlength=n_tiles))
        counts_qt = torch.stack(counts)  # [4, C * T]
        # cost in pixel elements, a slot (a gathered and scattered table row) counted as SLOT_PIXELS
        cell_pixels = (tile_size // 2) ** 2
        split_cost = counts_qt.sum(0) * (cell_pixels + SLOT_PIXELS)
        whole = split_cost > bins.tile_counts * (4 * cell_pixels + SLOT_PIXELS)
        # slots are ordered (quadrant, tile): exclusive cumsum in that order, then cell order; the
        # rows of whole tiles stay in ``rows`` unused (cheaper than compacting them out)
        flat_counts = counts_qt.view(-1)
        starts = (torch.cumsum(flat_counts, 0) - flat_counts).view(4, n_tiles).t().reshape(-1)
        counts_cell = counts_qt.masked_fill_(whole, 0).t().reshape(-1)
    return _Cells(
        torch.cat(rows + [pad]), starts, counts_cell, bins.tile_starts, bins.tile_counts * whole, 2, tile_size // 2
    )


def _plan_blocks(cells: _Cells, opacity_of_isect: Optional[Tensor]) -> List[_Block]:
    """Group non-empty whole tiles and cells (largest first) into blocks of about BLOCK_ELEMENTS.

    Inside a block of cells they are ordered by quadrant, then id: the pixels of one quadrant
    share a monomial basis (one matmul per quadrant), and the rows of a quadrant's cells ascend
    (cache-friendly gathers and scatters).

    Args:
        opacity_of_isect: [M + 1] opacity of each intersection's Gaussian (0 for the pad row), or
            None when no opacity exceeds ALPHA_MAX (no block can clamp).
    """
    n_sub = cells.per_side * cells.per_side
    cell_pixels = cells.size * cells.size
    pad_row = int(cells.rows[-1])
    blocks: List[_Block] = []
    for whole in (True, False):
        counts = cells.tile_counts if whole else cells.counts
        starts = cells.tile_starts if whole else cells.starts
        pixels = cell_pixels * n_sub if whole else cell_pixels
        order = torch.argsort(counts, descending=True)
        sorted_counts = counts.index_select(0, order).tolist()
        n_used = sorted_counts.index(0) if 0 in sorted_counts else len(sorted_counts)  # descending: zeros last
        begin = 0
        while begin < n_used:
            k = sorted_counts[begin]
            stop = min(n_used, begin + max(1, BLOCK_ELEMENTS // (pixels * k)))
            ids = order[begin:stop]
            if whole:
                ids = ids.sort().values
                bounds = [(-1, 0, len(ids))]
            else:
                quadrant = ids % n_sub
                ids = ids.index_select(0, torch.argsort(quadrant * len(counts) + ids))
                bounds, first = [], 0
                for q, count in enumerate(torch.bincount(quadrant, minlength=n_sub).tolist()):
                    if count:
                        bounds.append((q, first, first + count))
                    first += count
            slot = torch.arange(k, device=counts.device)
            filled = slot < counts.index_select(0, ids)[:, None]
            if whole:
                slots = torch.where(filled, starts.index_select(0, ids)[:, None] + slot, pad_row)
            else:
                pos = torch.where(filled, starts.index_select(0, ids)[:, None] + slot, len(cells.rows) - 1)
                slots = cells.rows.index_select(0, pos.view(-1)).view(pos.shape)
            can_clamp = opacity_of_isect is not None and bool(
                opacity_of_isect.index_select(0, slots.view(-1)).max() > ALPHA_MAX
            )
            blocks.append(_Block(ids, slots, can_clamp, bounds, pixels))
            begin = stop
    return blocks


@functools.lru_cache(maxsize=16)
def _cell_basis(tile_size: int, cell_size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """[s^2, P, 6] monomials (1, x, y, x^2, y^2, xy) of each cell's pixel centres, relative to the tile centre."""
    side = tile_size // cell_size
    offs = torch.arange(tile_size, dtype=dtype, device=device) + PIXEL_CENTRE - tile_size / 2.0
    py, px = torch.meshgrid(offs, offs, indexing="ij")  # [tile, tile]
    # [cell row, y in cell, cell column, x in cell] -> [cell row, cell column, y, x]
    px = px.reshape(side, cell_size, side, cell_size).permute(0, 2, 1, 3).reshape(side * side, -1)
    py = py.reshape(side, cell_size, side, cell_size).permute(0, 2, 1, 3).reshape(side * side, -1)
    return torch.stack([torch.ones_like(px), px, py, px * px, py * py, px * py], dim=-1)


class _Spares(threading.local):
    """Per-thread flat CPU buffers the rasteriser reuses between calls."""

    def __init__(self) -> None:
        self.buffers: List[Tensor] = []


_SPARES = _Spares()


def _take(numel: int, like: Tensor) -> Tensor:
    """A flat buffer of >= numel elements of like's dtype and device, a spare one when one fits.

    Fresh memory is expensive on CPU: glibc hands large freed blocks back to the kernel, and
    faulting the pages in again cost ~20% of a forward+backward here. Spares are best-fit.
    """
    if like.device.type == "cpu":
        spares = _SPARES.buffers
        fits = [i for i, b in enumerate(spares) if b.dtype == like.dtype and b.numel() >= numel]
        if fits:
            return spares.pop(min(fits, key=lambda i: spares[i].numel()))
    return like.new_empty(max(numel, 1))


def _give(buffer: Optional[Tensor]) -> None:
    """Return a buffer from ``_take`` once nothing uses it; keeps the largest SPARE_BUFFERS."""
    if buffer is not None and buffer.device.type == "cpu":
        spares = _SPARES.buffers
        spares.append(buffer)
        if len(spares) > SPARE_BUFFERS:
            spares.pop(min(range(len(spares)), key=lambda i: spares[i].numel()))


def _give_kept(holder: List[Optional[Tensor]]) -> None:
    """Give back the buffer a forward kept for its backward (once: the holder is emptied)."""
    buffer, holder[0] = holder[0], None
    _give(buffer)


class _Carver:
    """Consecutive contiguous views of a flat buffer."""

    def __init__(self, buffer: Tensor) -> None:
        self.buffer, self.offset = buffer, 0

    def __call__(self, *shape: int) -> Tensor:
        numel = math.prod(shape)
        view = self.buffer[self.offset : self.offset + numel].view(shape)
        self.offset += numel
        return view


@dataclass
class _Plan:
    """What the rasterising Function needs besides the differentiable inputs."""

    flat_ids: Tensor  # [M] Gaussian (c * N + n) of each intersection
    centre_x: Tensor  # [M] pixel centre of each intersection's tile
    centre_y: Tensor
    blocks: List[_Block]
    n_cells: int
    basis: Tensor  # [s^2, P, 6] pixel monomials per quadrant


def _block_forward(
    basis2: Tensor, rows: Tensor, block: _Block, need_grad: bool, alpha: Tensor, weights: Tensor, carve: _Carver
) -> Optional[Tensor]:
    """Compositing weights of one block, gsplat's rules, written into ``alpha`` and ``weights``.

    Layout [P, t, K] (pixel, cell, intersection): the exponents are one [P, 6] @ [6, t K] matmul
    and the scans run along the contiguous last axis.

    Args:
        basis2: [s^2, P, 6] pixel monomials of each quadrant times log2(e) (exp2 is about twice
            as fast as exp on CPU).
        rows: [t K, 6 + F] gathered intersection rows (coefficients, features).
        alpha: [P, t, K] output: alpha / (1 - alpha) when need_grad, else alpha.
        weights: [P, t, K] output: w = alpha * T_before.
        carve: workspace for two [P, t, K + 1] temporaries.

    Returns:
        For blocks where alpha can clamp (and need_grad), the [P, t, K] mask of unclamped alphas.
    """
    n_pix, n_cells, k = alpha.shape
    coeffs = rows[:, :N_COEFFS].t()  # [6, t K]
    for quadrant, first, stop in block.quadrants:  # log2(alpha)
        torch.mm(_basis_of(basis2, quadrant), coeffs[:, first * k : stop * k], out=alpha[:, first:stop].view(n_pix, -1))
    F.threshold_(alpha, -MAX_EXPONENT * LOG2_E, -MAX_EXPONENT * LOG2_E)  # clamp from below
    alpha.exp2_()
    F.threshold_(alpha, ALPHA_MIN, 0.0)  # gsplat skips alpha < 1/255
    unclamped = None
    if block.can_clamp:
        unclamped = alpha < ALPHA_MAX if need_grad else None
        F.hardtanh_(alpha, 0.0, ALPHA_MAX)
    one_minus, trans = carve(n_pix, n_cells, k + 1), carve(n_pix, n_cells, k + 1)
    one_minus[..., 0] = 1.0  # then 1 - alpha_j at j + 1
    torch.sub(one_minus[..., :1], alpha, out=one_minus[..., 1:])
    torch.cumprod(one_minus, -1, out=trans)  # [..., j] = transmittance before Gaussian j
    torch.mul(alpha, trans[..., :-1], out=weights)
    if float(trans[..., -1].min()) <= TRANSMITTANCE_MIN:
        # a pixel stops before the Gaussian that would take its transmittance to <= T_min
        keep = F.threshold_(trans, TRANSMITTANCE_MIN, 0.0).sign_()[..., 1:]  # reuses the buffer
        weights.mul_(keep)
        alpha.mul_(keep)
    if need_grad:
        alpha.div_(one_minus[..., 1:])
    return unclamped


def _build_table(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, depths: Tensor,
                 flat: Tensor, plan: "_Plan", table: Tensor, geometry: Tensor) -> None:
    """Fill the [M + 1, 6 + D + 2] intersection table and the [7, M] geometry rows
    (dx, dy, a, b, c, (Q d)_x, (Q d)_y), column by column ([M] gathers and ops: fastest on CPU)."""
    n_isect, n_feat = len(flat), features.shape[-1]
    n = opacities.shape[0]
    with torch.no_grad():
        gauss = flat if means2d.shape[0] == 1 else flat % n
        dx, dy, ca, cb, cc, qx, qy = geometry
        torch.index_select(means2d[..., 0].reshape(-1), 0, flat, out=dx).sub_(plan.centre_x)
        torch.index_select(means2d[..., 1].reshape(-1), 0, flat, out=dy).sub_(plan.centre_y)
        for i, dst in enumerate((ca, cb, cc)):
            torch.index_select(conics[..., i].reshape(-1), 0, flat, out=dst)
        torch.mul(ca, dx, out=qx).addcmul_(cb, dy)  # Q d
        torch.mul(cb, dx, out=qy).addcmul_(cc, dy)
        log_o = torch.log(opacities.clamp(min=MIN_OPACITY)).index_select(0, gauss)
        table[:n_isect, 0] = log_o.addcmul_(dx, qx, value=-0.5).addcmul_(dy, qy, value=-0.5)
        table[:n_isect, 1] = qx
        table[:n_isect, 2] = qy
        table[:n_isect, 3] = ca * -0.5
        table[:n_isect, 4] = cc * -0.5
        table[:n_isect, 5] = -cb
        table[:n_isect, N_COEFFS : N_COEFFS + n_feat] = features.reshape(-1, n_feat).index_select(
            0, flat if features.dim() == 3 else gauss
        )
        table[:n_isect, -2] = depths.reshape(-1).index_select(0, flat)
        table[:n_isect, -1] = 1.0
        table[n_isect] = 0.0
        table[n_isect, 0] = PAD_EXPONENT


def _basis_of(basis: Tensor, quadrant: int) -> Tensor:
    """[P, 6] monomials of one quadrant's pixels, or (quadrant -1) of the whole tile, quadrant-major."""
    return basis.reshape(-1, N_COEFFS) if quadrant < 0 else basis[quadrant]


class _Rasterize(torch.autograd.Function):
    """Intersection table and front-to-back compositing of cell blocks.

    Table rows [M + 1, 6 + D + 2]: exponent coefficients of the tile-local pixel position, the
    features, depth and 1 (for alpha); the last row is padding. The backward turns the row
    gradients into gradients of the per-Gaussian inputs in closed form and sums them per
    Gaussian with one index_add (autograd of the same ops costs ~10x more). One Function, so
    every large buffer comes from (and returns to) the per-thread spares.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx, means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, depths: Tensor, plan: _Plan
    ) -> Tensor:
        flat = plan.flat_ids
        n_isect, n_feat = len(flat), features.shape[-1]
        n_cols = N_COEFFS + n_feat + 2
        n_sub, cell_pixels = plan.basis.shape[0], plan.basis.shape[1]
        need_grad = bool(any(ctx.needs_input_grad[:5]))
        sizes = [b.slots.numel() * b.pixels for b in plan.blocks]  # t K P
        save = need_grad and 2 * sum(sizes) * means2d.element_size() <= SAVE_BUDGET_BYTES
        kept = _take((n_isect + 1) * n_cols + 7 * n_isect + (2 * sum(sizes) if save else 0), means2d)
        carve_kept = _Carver(kept)
        table = carve_kept(n_isect + 1, n_cols)
        geometry = carve_kept(7, n_isect)  # dx, dy, a, b, c, (Q d)_x, (Q d)_y

        _build_table(means2d, conics, opacities, features, depths, flat, plan, table, geometry)

        # ---- compositing
        basis2 = plan.basis * LOG2_E
        n_out = n_cols - N_COEFFS
        out = means2d.new_zeros(plan.n_cells, n_out, cell_pixels)  # channels before pixels: fast bmm
        # per block: rows, 2 [P, t, K + 1] temporaries and, unless kept, alpha and weights
        work = max((b.slots.numel() * n_cols + 2 * (s + b.slots.shape[0] * b.pixels) + (0 if save else 2 * s)
                    for b, s in zip(plan.blocks, sizes)), default=0)
        workspace = _take(work, means2d)
        saved: List[Tuple[Tensor, Tensor, Optional[Tensor]]] = []
        for block in plan.blocks:
            t, k = block.slots.shape
            carve = _Carver(workspace)
            rows = torch.index_select(table, 0, block.slots.view(-1), out=carve(t * k, n_cols))
            carve_out = carve_kept if save else carve
            alpha, weights = carve_out(block.pixels, t, k), carve_out(block.pixels, t, k)
            unclamped = _block_forward(basis2, rows, block, need_grad, alpha, weights, carve)
            feats_t = rows.view(t, k, n_cols)[..., N_COEFFS:].transpose(1, 2)  # [t, F, K]
            colours = torch.bmm(feats_t, weights.permute(1, 2, 0))  # [t, F, P]
            if block.quadrants[0][0] < 0:  # whole tiles: their pixels are quadrant-major, 4 cells each
                colours = colours.view(t, n_out, n_sub, cell_pixels).transpose(1, 2)
                out.view(-1, n_sub, n_out, cell_pixels).index_copy_(0, block.cells, colours)
            else:
                out.index_copy_(0, block.cells, colours)
            if save:
                saved.append((weights, alpha, unclamped))
        _give(workspace)
        ctx.plan, ctx.saved, ctx.kept = plan, saved, [kept]
        ctx.save_for_backward(means2d, conics, opacities, features, depths)
        if need_grad:  # back to the spares after backward, or when the graph is dropped without one
            weakref.finalize(ctx, _give_kept, ctx.kept).atexit = False
        else:
            _give_kept(ctx.kept)
        return out.transpose(1, 2)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out: Tensor):  # type: ignore[override]
        means2d, conics, opacities, features, depths = ctx.saved_tensors
        plan, kept = ctx.plan, ctx.kept[0]
        n_cams, n, feat_shape = means2d.shape[0], opacities.shape[0], features.shape
        flat = plan.flat_ids
        n_isect, n_feat = len(flat), feat_shape[-1]
        n_cols = N_COEFFS + n_feat + 2
        n_sub, cell_pixels = plan.basis.shape[0], plan.basis.shape[1]
        if kept is None:  # a second backward through the graph (retain_graph): rebuild
            kept = _take((n_isect + 1) * n_cols + 7 * n_isect, means2d)
            carve_kept = _Carver(kept)
            table, geometry = carve_kept(n_isect + 1, n_cols), carve_kept(7, n_isect)
            _build_table(means2d, conics, opacities, features, depths, flat, plan, table, geometry)
        carve_kept = _Carver(kept)
        table = carve_kept(n_isect + 1, n_cols)
        dx, dy, ca, cb, cc, qx, qy = carve_kept(7, n_isect)
        grad_out = grad_out.contiguous()
        recompute = not ctx.saved
        # per block: rows, h, g, its cumsum (reused for the per-slot gradients), [t, F, K] feature
        # gradients (and the forward's buffers when recomputing)
        work = max(
            (b.slots.numel() * (n_cols + 3 * b.pixels + n_feat + 2)
             + (4 * b.slots.numel() * b.pixels + 2 * b.slots.shape[0] * b.pixels if recompute else 0)
             for b in plan.blocks),
            default=0,
        )
        work = max(work, (7 + n_feat) * n_isect)
        workspace = _take(work + n_cols * (n_isect + 1), table)
        # [columns, rows]
        grad_table = workspace[work : work + n_cols * (n_isect + 1)].view(n_cols, n_isect + 1).zero_()
        for i, block in enumerate(plan.blocks):
            t, k = block.slots.shape
            n_pix = block.pixels
            carve = _Carver(workspace)
            rows = torch.index_select(table, 0, block.slots.view(-1), out=carve(t * k, n_cols))
            feats_t = rows.view(t, k, n_cols)[..., N_COEFFS:].transpose(1, 2)  # [t, F, K]
            h, g, later, g_feat = carve(t, n_pix, k), carve(n_pix, t, k), carve(n_pix, t, k), carve(t, n_feat + 2, k)
            if recompute:
                ratio, weights = carve(n_pix, t, k), carve(n_pix, t, k)
                unclamped = _block_forward(plan.basis * LOG2_E, rows, block, True, ratio, weights, carve)
            else:
                weights, ratio, unclamped = ctx.saved[i]
            if block.quadrants[0][0] < 0:  # whole tiles: 4 cells each, pixels quadrant-major
                g_pix = grad_out.view(-1, n_sub, cell_pixels, n_feat + 2).index_select(0, block.cells)
                g_pix = g_pix.view(t, n_pix, n_feat + 2)
            else:
                g_pix = grad_out.index_select(0, block.cells)  # [t, P, F]
            # with h_k = dL/dC . f_k:  dL/dalpha_k = T_k h_k - (sum_{j>k} w_j h_j) / (1 - alpha_k);
            # dalpha/dlog(alpha) = alpha, so dL/dlog(alpha_k) = w_k h_k - ratio_k * sum_{j>k} w_j h_j
            torch.bmm(g_pix, feats_t, out=h)
            torch.mul(h.permute(1, 0, 2), weights, out=g)  # [P, t, K]
            torch.cumsum(g, -1, out=later)
            later.sub_(later[..., -1:].clone())
            g.addcmul_(later, ratio)
            if unclamped is not None:
                g.mul_(unclamped)
            per_slot = later.view(-1)[: n_cols * t * k].view(n_cols, t * k)  # later is free again
            for quadrant, first, stop in block.quadrants:
                torch.mm(
                    _basis_of(plan.basis, quadrant).t(), g[:, first:stop].view(n_pix, -1),
                    out=per_slot[:N_COEFFS, first * k : stop * k],
                )
            torch.bmm(g_pix.transpose(1, 2), weights.permute(1, 0, 2), out=g_feat)
            per_slot[N_COEFFS:].view(n_feat + 2, t, k).copy_(g_feat.transpose(0, 1))
            grad_table.index_add_(1, block.slots.view(-1), per_slot)
        ctx.saved = None  # a second backward (retain_graph) recomputes
        ctx.kept[0] = None

        # ---- rows -> Gaussians: derivatives of (c0 .. c5) = (log o - d.Qd / 2, Qd, -a/2, -c/2, -b)
        # with d = mean - tile centre, then one index_add per Gaussian
        g0, g1, g2, g3, g4, g5 = grad_table[:N_COEFFS, :n_isect]
        per_isect = workspace[: (7 + n_feat) * n_isect].view(7 + n_feat, n_isect)  # the blocks are done
        torch.mul(ca, g1, out=per_isect[0]).addcmul_(cb, g2).addcmul_(g0, qx, value=-1.0)  # d / d mean_x
        torch.mul(cb, g1, out=per_isect[1]).addcmul_(cc, g2).addcmul_(g0, qy, value=-1.0)  # d / d mean_y
        half_g0 = g0 * 0.5
        torch.addcmul(g1, half_g0, dx, value=-1.0, out=per_isect[2]).mul_(dx).add_(g3, alpha=-0.5)  # d / d a
        torch.addcmul(g1, g0, dx, value=-1.0, out=per_isect[3]).mul_(dy).addcmul_(dx, g2).sub_(g5)  # d / d b
        torch.addcmul(g2, half_g0, dy, value=-1.0, out=per_isect[4]).mul_(dy).add_(g4, alpha=-0.5)  # d / d c
        per_isect[5] = grad_table[-2, :n_isect]  # d / d depth
        per_isect[6] = g0  # d / d log(opacity)
        per_isect[7:] = grad_table[N_COEFFS : N_COEFFS + n_feat, :n_isect]
        per_gauss = per_isect.new_zeros(7 + n_feat, n_cams * n).index_add_(1, flat, per_isect)
        _give(workspace)
        _give(kept)
        grad_means2d = per_gauss[0:2].t().reshape(n_cams, n, 2)
        grad_conics = per_gauss[2:5].t().reshape(n_cams, n, 3)
        grad_depths = per_gauss[5].reshape(n_cams, n)
        grad_log_o = per_gauss[6].reshape(n_cams, n).sum(0)
        grad_opacities = torch.where(opacities >= MIN_OPACITY, grad_log_o / opacities.clamp(min=MIN_OPACITY), 0.0)
        grad_features = per_gauss[7:].t()
        if len(feat_shape) == 3:
            grad_features = grad_features.reshape(feat_shape)
        else:
            grad_features = grad_features.reshape(n_cams, n, n_feat).sum(0)
        return grad_means2d, grad_conics, grad_opacities, grad_features, grad_depths, None


def _cells_to_image(tiled: Tensor, n_cams: int, bins: TileBins, cells: _Cells, width: int, height: int) -> Tensor:
    """[C*T*s^2, P, F] cell layout -> [C, H, W, F] image."""
    n_feat, side, size = tiled.shape[-1], cells.per_side, cells.size
    img = tiled.reshape(n_cams, bins.tiles_y, bins.tiles_x, side, side, size, size, n_feat)
    img = img.permute(0, 1, 3, 5, 2, 4, 6, 7).reshape(
        n_cams, bins.tiles_y * side * size, bins.tiles_x * side * size, n_feat
    )
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
        means ... far_plane: the contract's (shapes and units: ``contract.RasterBackend``).
        tile_size: tile edge in pixels; only changes which far tails of Gaussians are cut.

    Returns:
        RasterOutputs; gradients reach means, quats, scales, opacities, features and viewmats,
        and ``means2d.grad`` holds dL/d(pixel centre) after backward.
    """
    check_inputs(means, quats, scales, opacities, features, viewmats, Ks)
    n_cams, n = viewmats.shape[0], means.shape[-2]
    n_channels = features.shape[-1]
    if backgrounds is not None and tuple(backgrounds.shape) != (n_cams, n_channels):
        raise ValueError(
            f"rasterize: backgrounds has shape {tuple(backgrounds.shape)}, expected [C={n_cams}, D={n_channels}]"
        )
    proj = project_per_camera(project_gaussians, means, quats, scales, viewmats, Ks, width, height, near_plane, far_plane)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    bins = bin_gaussians(means2d, proj.radii, proj.depths, width, height, tile_size, proj.conics, opacities)
    cells = _split_cells(bins, tile_size)

    # tile centres of the intersections, in float32 (exact: tile ids < 2^24)
    with torch.no_grad():
        tile = bins.tile_ids.to(torch.float32)
        n_tiles = bins.tiles_x * bins.tiles_y
        if n_cams > 1:
            tile = tile - torch.floor((tile + 0.5) / n_tiles) * n_tiles
        row = torch.floor((tile + 0.5) / bins.tiles_x)
        centre_x = ((tile - row * bins.tiles_x) * tile_size + tile_size / 2.0).to(means2d.dtype)
        centre_y = (row * tile_size + tile_size / 2.0).to(means2d.dtype)
    opacity_of_isect = None
    if bool((opacities.detach() > ALPHA_MAX).any()):
        opacity_of_isect = torch.cat([opacities.detach().index_select(0, bins.flat_ids % n), opacities.new_zeros(1)])
    basis = _cell_basis(tile_size, cells.size, means2d.dtype, means2d.device)
    plan = _Plan(
        bins.flat_ids, centre_x, centre_y, _plan_blocks(cells, opacity_of_isect),
        n_cams * n_tiles * cells.per_side**2, basis,
    )
    tiled = _Rasterize.apply(means2d, proj.conics, opacities, features, proj.depths, plan)
    image = _cells_to_image(tiled, n_cams, bins, cells, width, height)
    colour, depth_sum, alpha = image[..., :n_channels], image[..., n_channels : n_channels + 1], image[..., -1:]
    if backgrounds is not None:
        colour = colour + (1.0 - alpha) * backgrounds[:, None, None, :]
    depth = depth_sum / alpha.clamp(min=MIN_ALPHA_FOR_DEPTH)
    return RasterOutputs(
        render=colour, depth=depth, alpha=alpha, means2d=means2d, radii=proj.radii, visible=proj.radii > 0
    )

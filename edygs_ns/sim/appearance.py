"""Appearance of the synthetic scene: procedural textures, bilinear texture lookup, Lambert shading.

Every texture is procedural and deterministic from a seeded generator: blobs, discs, coloured
patches, a faint checker and text-like strokes, dense enough for SIFT to register every view.
Values are LINEAR intensity in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence, Tuple

import numpy as np

#: Texels per world unit of the procedural textures (sets how fine their detail is).
TEXELS_PER_UNIT = 64
#: Smallest and largest texture side in texels.
TEXTURE_MIN_TEXELS = 32
TEXTURE_MAX_TEXELS = 1024
#: Texture values are clipped into this linear range, so log intensity stays finite and lively.
TEXTURE_MIN_VALUE = 0.06
TEXTURE_MAX_VALUE = 0.94
#: Features stamped per square world unit of texture.
BLOBS_PER_UNIT2 = 4.0
DISCS_PER_UNIT2 = 3.0
PATCHES_PER_UNIT2 = 2.5
MARKS_PER_UNIT2 = 8.0
#: Size ranges of the stamped features, world units (blob sigma, disc radius, patch side, stroke).
BLOB_SIGMA_RANGE = (0.04, 0.2)
DISC_RADIUS_RANGE = (0.03, 0.12)
PATCH_SIDE_RANGE = (0.08, 0.4)
MARK_LENGTH_RANGE = (0.08, 0.3)
MARK_THICKNESS_RANGE = (0.02, 0.05)
#: Checker cell side range (world units) and how strongly the checker modulates the base.
CHECKER_CELL_RANGE = (0.1, 0.3)
CHECKER_STRENGTH = 0.08
#: Standard deviation of the per-texel noise added last.
TEXEL_NOISE_SIGMA = 0.02
#: Range of the base (background) colour of a surface texture.
BASE_COLOR_RANGE = (0.25, 0.7)
#: Saturation of the stamped feature colours of the room (1 = fully random RGB, 0 = grey).
ROOM_SATURATION = 0.45
#: Lambert shading: value = albedo * (AMBIENT + DIFFUSE * cos), cos = max(n . l, 0) on the
#: moving objects (closed, seen from outside) and |n . l| on the (two-sided) quads.
AMBIENT = 0.45
DIFFUSE = 0.55
#: Direction towards the light (normalised at use).
LIGHT_DIRECTION = (0.35, 0.8, 0.5)


def _stamp(img: np.ndarray, r0: int, r1: int, c0: int, c1: int, alpha: np.ndarray, color: np.ndarray) -> None:
    """Alpha-blend ``color`` into ``img[r0:r1, c0:c1]`` with weights ``alpha`` [r1-r0, c1-c0]."""
    window = img[r0:r1, c0:c1]
    window += alpha[..., None] * (color - window)


def procedural_texture(rng: np.random.Generator, size_u: float, size_v: float,
                       base_range: Tuple[float, float] = BASE_COLOR_RANGE, detail: float = 1.0,
                       saturation: float = ROOM_SATURATION) -> np.ndarray:
    """A non-repetitive texture for a surface of size_u x size_v world units.

    Layers (in order): base colour, faint checker, soft Gaussian blobs, hard discs, coloured
    rectangular patches, thin text-like strokes, per-texel noise.

    Args:
        rng: source of all randomness (deterministic textures from a seeded generator).
        size_u: surface extent along the texture columns, world units.
        size_v: surface extent along the texture rows, world units.
        base_range: range of the base colour channels.
        detail: multiplier on the feature densities.
        saturation: how far feature colours stray from grey (0 grey, 1 fully random RGB).

    Returns:
        [Tv, Tu, 3] float32 linear albedo in [TEXTURE_MIN_VALUE, TEXTURE_MAX_VALUE].
    """
    tu = int(np.clip(round(size_u * TEXELS_PER_UNIT), TEXTURE_MIN_TEXELS, TEXTURE_MAX_TEXELS))
    tv = int(np.clip(round(size_v * TEXELS_PER_UNIT), TEXTURE_MIN_TEXELS, TEXTURE_MAX_TEXELS))
    texels_per_unit = tu / size_u
    area = size_u * size_v
    img = np.empty((tv, tu, 3), dtype=np.float64)
    img[:] = rng.uniform(*base_range, size=3)

    cell = rng.uniform(*CHECKER_CELL_RANGE) * texels_per_unit
    rows, cols = np.mgrid[0:tv, 0:tu]
    checker = ((rows // cell + cols // cell) % 2) * 2.0 - 1.0
    img *= (1.0 + CHECKER_STRENGTH * checker)[..., None]

    def n_features(density: float) -> int:
        return max(1, int(round(density * detail * area)))

    def color() -> np.ndarray:
        rgb = rng.uniform(0.0, 1.0, size=3)
        return rgb.mean() + saturation * (rgb - rgb.mean())

    for _ in range(n_features(BLOBS_PER_UNIT2)):
        sigma = rng.uniform(*BLOB_SIGMA_RANGE) * texels_per_unit
        cy, cx = rng.uniform(0, tv), rng.uniform(0, tu)
        reach = 3.0 * sigma
        r0, r1 = int(max(cy - reach, 0)), int(min(cy + reach + 1, tv))
        c0, c1 = int(max(cx - reach, 0)), int(min(cx + reach + 1, tu))
        if r1 <= r0 or c1 <= c0:
            continue
        yy, xx = np.mgrid[r0:r1, c0:c1]
        alpha = np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2.0 * sigma**2))
        _stamp(img, r0, r1, c0, c1, alpha, color())

    for _ in range(n_features(DISCS_PER_UNIT2)):
        radius = rng.uniform(*DISC_RADIUS_RANGE) * texels_per_unit
        cy, cx = rng.uniform(0, tv), rng.uniform(0, tu)
        r0, r1 = int(max(cy - radius, 0)), int(min(cy + radius + 1, tv))
        c0, c1 = int(max(cx - radius, 0)), int(min(cx + radius + 1, tu))
        if r1 <= r0 or c1 <= c0:
            continue
        yy, xx = np.mgrid[r0:r1, c0:c1]
        alpha = (((yy - cy) ** 2 + (xx - cx) ** 2) <= radius**2).astype(np.float64)
        _stamp(img, r0, r1, c0, c1, alpha, color())

    for _ in range(n_features(PATCHES_PER_UNIT2)):
        h, w = rng.uniform(*PATCH_SIDE_RANGE, size=2) * texels_per_unit
        r0, c0 = int(rng.uniform(0, tv)), int(rng.uniform(0, tu))
        r1, c1 = min(r0 + max(int(h), 1), tv), min(c0 + max(int(w), 1), tu)
        _stamp(img, r0, r1, c0, c1, np.ones((r1 - r0, c1 - c0)), color())

    for _ in range(n_features(MARKS_PER_UNIT2)):
        length = rng.uniform(*MARK_LENGTH_RANGE) * texels_per_unit
        thick = rng.uniform(*MARK_THICKNESS_RANGE) * texels_per_unit
        h, w = (length, thick) if rng.uniform() < 0.5 else (thick, length)
        r0, c0 = int(rng.uniform(0, tv)), int(rng.uniform(0, tu))
        r1, c1 = min(r0 + max(int(h), 1), tv), min(c0 + max(int(w), 1), tu)
        ink = rng.choice([TEXTURE_MIN_VALUE, TEXTURE_MAX_VALUE])
        _stamp(img, r0, r1, c0, c1, np.ones((r1 - r0, c1 - c0)), np.full(3, ink))

    img += rng.normal(0.0, TEXEL_NOISE_SIGMA, size=img.shape)
    return np.clip(img, TEXTURE_MIN_VALUE, TEXTURE_MAX_VALUE).astype(np.float32)


def _bilinear(flat: np.ndarray, offset: Any, tu: Any, tv: Any, a: np.ndarray, b: np.ndarray,
              wrap_u: bool) -> np.ndarray:
    """Bilinear lookup in row-major textures stored back to back in ``flat`` [sum Tv*Tu, 3].

    ``offset`` (first texel), ``tu`` and ``tv`` (texture sizes) are scalars or [N] arrays, one
    per sample; a, b are [N] coordinates in [0, 1] along columns and rows.
    """
    half = np.float32(0.5)
    x = np.asarray(a, dtype=np.float32) * np.asarray(tu, dtype=np.float32) - half
    y = np.asarray(b, dtype=np.float32) * np.asarray(tv, dtype=np.float32) - half
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0)[:, None]  # float32 throughout: mixing in float64 makes the blend ~5x slower
    fy = (y - y0)[:, None]
    x0 = x0.astype(np.int64)
    y0 = y0.astype(np.int64)
    if wrap_u:
        xa, xb = x0 % tu, (x0 + 1) % tu
    else:
        xa, xb = np.clip(x0, 0, tu - 1), np.clip(x0 + 1, 0, tu - 1)
    row_a = offset + np.clip(y0, 0, tv - 1) * tu
    row_b = offset + np.clip(y0 + 1, 0, tv - 1) * tu
    flat = np.asarray(flat, dtype=np.float32)
    top = np.take(flat, row_a + xa, axis=0)  # np.take: several times faster than flat[idx]
    top += fx * (np.take(flat, row_a + xb, axis=0) - top)
    bottom = np.take(flat, row_b + xa, axis=0)
    bottom += fx * (np.take(flat, row_b + xb, axis=0) - bottom)
    top += fy * (bottom - top)
    return top


def sample_bilinear(texture: np.ndarray, a: np.ndarray, b: np.ndarray, wrap_u: bool = False) -> np.ndarray:
    """Bilinear texture lookup.

    Args:
        texture: [Tv, Tu, C] texels.
        a: [N] coordinate along columns in [0, 1] (texel centres at (i + 0.5) / Tu).
        b: [N] coordinate along rows in [0, 1].
        wrap_u: wrap around in a (for the sphere's longitude); otherwise clamp at the edges.

    Returns:
        [N, C] interpolated values.
    """
    tv, tu = texture.shape[:2]
    return _bilinear(texture.reshape(tv * tu, -1), 0, tu, tv, a, b, wrap_u)


@dataclass(frozen=True)
class TextureAtlas:
    """Q textures of different sizes stored back to back, for one lookup over many quads.

    Attributes:
        texels: [sum Tv*Tu, 3] float32 texels, each texture row-major.
        offsets: [Q] int64 index of each texture's first texel.
        widths: [Q] int64 Tu of each texture.
        heights: [Q] int64 Tv of each texture.
    """

    texels: np.ndarray
    offsets: np.ndarray
    widths: np.ndarray
    heights: np.ndarray

    @classmethod
    def from_textures(cls, textures: Sequence[np.ndarray]) -> "TextureAtlas":
        """Pack [Tv, Tu, 3] textures."""
        sizes = np.array([t.shape[0] * t.shape[1] for t in textures], dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        texels = np.concatenate([t.reshape(-1, t.shape[-1]) for t in textures]).astype(np.float32)
        return cls(texels, offsets, np.array([t.shape[1] for t in textures], dtype=np.int64),
                   np.array([t.shape[0] for t in textures], dtype=np.int64))

    def sample(self, ids: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """[N, 3] bilinear lookups at coordinates (a, b) in [0, 1] of textures ``ids`` [N]."""
        return _bilinear(self.texels, self.offsets[ids], self.widths[ids], self.heights[ids], a, b, wrap_u=False)


def lambert(normals: np.ndarray, two_sided: bool) -> np.ndarray:
    """[N] Lambert factor AMBIENT + DIFFUSE * cos for [N, 3] unit normals (cos = |n . l| when
    ``two_sided``, else max(n . l, 0))."""
    light = np.asarray(LIGHT_DIRECTION, float)
    cos = normals @ (light / np.linalg.norm(light))
    cos = np.abs(cos) if two_sided else np.maximum(cos, 0.0)
    return AMBIENT + DIFFUSE * cos

"""The built-in synthetic 3D scene and a vectorised numpy ray caster for it.

The scene is a textured room (back wall, floor, ceiling, two side walls) holding a few static
textured boxes at different depths, plus one moving textured sphere (the dynamic region).
Every texture is procedural and deterministic from a seed: blobs, discs, coloured patches,
a faint checker and text-like strokes, dense enough for SIFT to register every view.

Conventions: world units are arbitrary ("units"), y is up; the room is open behind the camera
(+z side). Cameras use the OpenGL convention of docs/layouts.md (x right, y up, looking down
-z; ``c2w`` is a 4x4 camera-to-world matrix). Rendered values are LINEAR intensity in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import Any, List, Optional, Sequence, Tuple

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
#: sphere and |n . l| on the (two-sided) quads.
AMBIENT = 0.45
DIFFUSE = 0.55
#: Direction towards the light (normalised at use).
LIGHT_DIRECTION = (0.35, 0.8, 0.5)
#: Radiance of rays that hit nothing (the open side of the room).
BACKGROUND_VALUE = 0.05
#: Rays hitting closer than this are ignored (avoids self-hits at t = 0).
RAY_T_MIN = 1e-6
#: Rays more parallel than this to a plane do not hit it.
PARALLEL_EPS = 1e-9
#: Grey weights (ITU-R BT.601) turning linear RGB into the event camera's intensity.
GREY_WEIGHTS = (0.299, 0.587, 0.114)

#: Room bounds (x, y, z) in world units: floor at y_min, back wall at z_min, open at z_max.
ROOM_MIN = (-2.0, -1.2, -4.0)
ROOM_MAX = (2.0, 1.6, 2.5)
#: Static boxes standing on the floor: (centre x, centre z, size x, size y, size z).
BOX_LAYOUT = (
    (-1.25, -3.0, 0.8, 0.9, 0.7),
    (1.25, -1.0, 0.5, 0.6, 0.5),
    (0.95, -3.3, 0.45, 1.9, 0.45),
)
#: Uniform jitter (world units) the seed applies to each box's centre x and z.
BOX_JITTER = 0.12
#: Largest yaw (radians) the seed gives a box about the vertical axis.
BOX_MAX_YAW = 0.5
#: Base colour range of the moving sphere (saturated, so it stands out from the room).
SPHERE_BASE_RANGE = (0.1, 0.9)
#: Saturation of the sphere's feature colours.
SPHERE_SATURATION = 1.0
#: Feature density multiplier on the sphere texture (it is small; make it busy).
SPHERE_DETAIL_SCALE = 3.0


@dataclass(frozen=True)
class Quad:
    """A textured rectangle origin + a * edge_u + b * edge_v, with a, b in [0, 1].

    Attributes:
        origin: [3] world position of the (a=0, b=0) corner.
        edge_u: [3] first edge (texture columns run along it).
        edge_v: [3] second edge, perpendicular to edge_u (texture rows run along it).
        texture: [Tv, Tu, 3] float32 linear albedo in [0, 1].
        box_centre: [3] centre of the closed box this quad is a face of (its back faces are
            culled), or None for a free-standing quad seen from both sides.
    """

    origin: np.ndarray
    edge_u: np.ndarray
    edge_v: np.ndarray
    texture: np.ndarray
    box_centre: Optional[np.ndarray] = None

    @property
    def normal(self) -> np.ndarray:
        """[3] unit normal (either side is visible; shading uses |n . l|)."""
        n = np.cross(self.edge_u, self.edge_v)
        return n / np.linalg.norm(n)


@dataclass(frozen=True)
class Sphere:
    """The moving object's shape and appearance; its pose is an ObjectState.

    Attributes:
        radius: world units.
        texture: [Tv, Tu, 3] float32 linear albedo, equirectangular (columns = longitude).
    """

    radius: float
    texture: np.ndarray


@dataclass(frozen=True)
class ObjectState:
    """Pose of the moving sphere at one instant.

    Attributes:
        centre: [3] world position of the sphere centre.
        rotation: [3, 3] object-to-world rotation (spins the texture).
    """

    centre: np.ndarray
    rotation: np.ndarray


@dataclass(frozen=True)
class QuadStack:
    """The geometry of Q quads stacked for vectorised intersection.

    Attributes:
        origins: [Q, 3] corners.
        normals: [Q, 3] unit normals.
        edges_u: [Q, 3] first edges.
        edges_v: [Q, 3] second edges.
        len2_u: [Q] squared length of edges_u.
        len2_v: [Q] squared length of edges_v.
        centres: [Q, 3] centres of the quads.
        outward: [Q, 3] centre minus box centre for box faces (a face is hidden when the camera
            is behind it), zero for free-standing quads (never culled).
    """

    origins: np.ndarray
    normals: np.ndarray
    edges_u: np.ndarray
    edges_v: np.ndarray
    len2_u: np.ndarray
    len2_v: np.ndarray
    centres: np.ndarray
    outward: np.ndarray

    @classmethod
    def from_quads(cls, quads: Sequence[Quad]) -> "QuadStack":
        """Stack the geometry of ``quads`` (textures are left out)."""
        origins = np.stack([q.origin for q in quads])
        normals = np.stack([q.normal for q in quads])
        edges_u = np.stack([q.edge_u for q in quads])
        edges_v = np.stack([q.edge_v for q in quads])
        centres = origins + 0.5 * (edges_u + edges_v)
        outward = np.stack([np.zeros(3) if q.box_centre is None else c - q.box_centre for q, c in zip(quads, centres)])
        return cls(origins, normals, edges_u, edges_v, np.sum(edges_u**2, axis=1), np.sum(edges_v**2, axis=1),
                   centres, outward)

    def facing(self, eye: np.ndarray) -> np.ndarray:
        """[Q] bool: quads that can be seen from ``eye`` (back faces of boxes are dropped)."""
        return np.einsum("qc,qc->q", eye[None, :] - self.centres, self.outward) >= 0.0


@dataclass(frozen=True)
class Scene:
    """Static geometry plus the (pose-less) moving sphere.

    Attributes:
        quads: static textured rectangles (room and boxes).
        sphere: the moving object.
        room_min: [3] lower corner of the room box.
        room_max: [3] upper corner of the room box.
    """

    quads: Tuple[Quad, ...]
    sphere: Sphere
    room_min: np.ndarray
    room_max: np.ndarray

    @cached_property
    def quad_stack(self) -> QuadStack:
        """The static quads stacked for vectorised ray casting (built once)."""
        return QuadStack.from_quads(self.quads)

    @cached_property
    def atlas(self) -> TextureAtlas:
        """The static quads' textures packed for one lookup (built once)."""
        return TextureAtlas.from_textures([q.texture for q in self.quads])

    @cached_property
    def quad_shading(self) -> np.ndarray:
        """[Q] float32 Lambert factor of each static quad (seen from either side)."""
        return _shade(self.quad_stack.normals, two_sided=True).astype(np.float32)

    @property
    def room_diameter(self) -> float:
        """Diagonal of the room box in world units."""
        return float(np.linalg.norm(self.room_max - self.room_min))


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics in pixels (pixel centres at integer + 0.5).

    Attributes:
        width: image width in pixels.
        height: image height in pixels.
        fl_x: focal length along x in pixels.
        fl_y: focal length along y in pixels.
        cx: principal point x in pixels.
        cy: principal point y in pixels.
    """

    width: int
    height: int
    fl_x: float
    fl_y: float
    cx: float
    cy: float

    @classmethod
    def from_fov(cls, width: int, height: int, fov_x_deg: float) -> "PinholeCamera":
        """Square pixels, principal point at the image centre, horizontal field of view in degrees."""
        if width <= 0 or height <= 0:
            raise ValueError(f"PinholeCamera: image size must be positive, got {width}x{height}")
        if not 0.0 < fov_x_deg < 180.0:
            raise ValueError(f"PinholeCamera: fov_x_deg must lie in (0, 180), got {fov_x_deg}")
        focal = 0.5 * width / np.tan(np.radians(0.5 * fov_x_deg))
        return cls(width, height, float(focal), float(focal), 0.5 * width, 0.5 * height)

    def ray_directions(self, c2w: np.ndarray, supersample: int) -> np.ndarray:
        """Unit world-space ray directions through a supersample x supersample grid per pixel.

        Args:
            c2w: [4, 4] camera-to-world, OpenGL convention.
            supersample: sub-pixel samples per pixel side (>= 1).

        Returns:
            [H*s, W*s, 3] float32 unit directions, sub-pixel rows/columns in image order.
        """
        d_cam = _camera_space_directions(self, int(supersample))
        return d_cam @ np.asarray(c2w, dtype=np.float64)[:3, :3].T.astype(np.float32)


@lru_cache(maxsize=4)
def _camera_space_directions(camera: PinholeCamera, supersample: int) -> np.ndarray:
    """[H*s, W*s, 3] float32 unit camera-space (OpenGL) directions of the sub-pixel centres."""
    s = supersample
    cols = (np.arange(camera.width * s) + 0.5) / s
    rows = (np.arange(camera.height * s) + 0.5) / s
    u, v = np.meshgrid(cols, rows)
    d_cam = np.stack([(u - camera.cx) / camera.fl_x, -(v - camera.cy) / camera.fl_y, -np.ones_like(u)], axis=-1)
    d_cam /= np.linalg.norm(d_cam, axis=-1, keepdims=True)
    d_cam = d_cam.astype(np.float32)
    d_cam.flags.writeable = False
    return d_cam


# ----------------------------------------------------------------------------------------------
# Procedural textures
# ----------------------------------------------------------------------------------------------


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


# ----------------------------------------------------------------------------------------------
# Scene construction
# ----------------------------------------------------------------------------------------------


def _textured_quad(rng: np.random.Generator, origin: Sequence[float], edge_u: Sequence[float],
                   edge_v: Sequence[float], box_centre: Optional[np.ndarray] = None) -> Quad:
    eu, ev = np.asarray(edge_u, float), np.asarray(edge_v, float)
    texture = procedural_texture(rng, float(np.linalg.norm(eu)), float(np.linalg.norm(ev)))
    return Quad(np.asarray(origin, float), eu, ev, texture, box_centre)


def _room_quads(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray) -> List[Quad]:
    """Back wall, floor, ceiling, left and right walls of the box [lo, hi] (open at z = hi.z)."""
    size = hi - lo
    ex, ey, ez = np.diag(size)
    return [
        _textured_quad(rng, lo, ex, ey),  # back wall, z = lo.z
        _textured_quad(rng, lo, ex, ez),  # floor, y = lo.y
        _textured_quad(rng, lo + ey, ex, ez),  # ceiling, y = hi.y
        _textured_quad(rng, lo, ez, ey),  # left wall, x = lo.x
        _textured_quad(rng, lo + ex, ez, ey),  # right wall, x = hi.x
    ]


def _box_quads(rng: np.random.Generator, centre: np.ndarray, size: np.ndarray, yaw: float) -> List[Quad]:
    """Six textured faces of a box rotated by ``yaw`` radians about the vertical axis."""
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    ex, ey, ez = (rot @ np.diag(size)).T
    corner = centre - 0.5 * (ex + ey + ez)
    faces = ((corner, ex, ey), (corner + ez, ex, ey), (corner, ez, ey), (corner + ex, ez, ey), (corner, ex, ez),
             (corner + ey, ex, ez))
    return [_textured_quad(rng, origin, eu, ev, centre) for origin, eu, ev in faces]


def build_scene(seed: int, object_radius: float) -> Scene:
    """The built-in room scene; textures and box placement are deterministic from ``seed``.

    Args:
        seed: random seed.
        object_radius: radius of the moving sphere, world units.
    """
    if object_radius <= 0:
        raise ValueError(f"build_scene: object_radius must be positive, got {object_radius}")
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(ROOM_MIN, float), np.asarray(ROOM_MAX, float)
    quads = _room_quads(rng, lo, hi)
    for cx, cz, sx, sy, sz in BOX_LAYOUT:
        jitter = rng.uniform(-BOX_JITTER, BOX_JITTER, size=2)
        centre = np.array([cx + jitter[0], lo[1] + 0.5 * sy, cz + jitter[1]])
        quads += _box_quads(rng, centre, np.array([sx, sy, sz]), rng.uniform(-BOX_MAX_YAW, BOX_MAX_YAW))
    circumference = 2.0 * np.pi * object_radius
    sphere_tex = procedural_texture(rng, circumference, 0.5 * circumference, SPHERE_BASE_RANGE, SPHERE_DETAIL_SCALE,
                                    SPHERE_SATURATION)
    return Scene(tuple(quads), Sphere(float(object_radius), sphere_tex), lo, hi)


# ----------------------------------------------------------------------------------------------
# Rendering
# ----------------------------------------------------------------------------------------------


def _intersect_quads(quads: QuadStack, ids: np.ndarray, origin: np.ndarray,
                     dirs: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray distances and texture coordinates of the quads ``ids`` at once.

    Args:
        quads: the stacked static quads.
        ids: [Q'] indices of the quads to test.
        origin: [3] common ray origin.
        dirs: [N, 3] float32 ray directions.

    Returns:
        t: [N, Q'] float32 distance along each ray (inf where it misses that quad).
        a, b: [N, Q'] float32 texture coordinates of the hit points along edge_u and edge_v.
    """
    rel = origin[None, :] - quads.origins[ids]  # [Q', 3]
    normals, edges_u, edges_v = quads.normals[ids], quads.edges_u[ids], quads.edges_v[ids]
    o_n = np.einsum("qc,qc->q", rel, normals).astype(np.float32)
    o_u = np.einsum("qc,qc->q", rel, edges_u).astype(np.float32)
    o_v = np.einsum("qc,qc->q", rel, edges_v).astype(np.float32)
    d_n = dirs @ normals.T.astype(np.float32)
    d_n[np.abs(d_n) <= PARALLEL_EPS] = np.inf
    t = np.divide(-o_n, d_n, out=d_n)
    a = dirs @ edges_u.T.astype(np.float32)
    a *= t
    a += o_u
    a /= quads.len2_u[ids].astype(np.float32)
    b = dirs @ edges_v.T.astype(np.float32)
    b *= t
    b += o_v
    b /= quads.len2_v[ids].astype(np.float32)
    miss = (t <= RAY_T_MIN) | (a < 0.0) | (a > 1.0) | (b < 0.0) | (b > 1.0)
    t[miss] = np.inf
    return t, a, b


def _intersect_sphere(centre: np.ndarray, radius: float, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Nearest positive ray distance to the sphere (inf on a miss) for [N, 3] unit rays."""
    oc = origin - centre
    half_b = dirs @ oc
    c = oc @ oc - radius**2
    disc = half_b**2 - c
    root = np.sqrt(np.maximum(disc, 0.0))
    near, far = -half_b - root, -half_b + root
    t = np.where(near > RAY_T_MIN, near, far)
    return np.where((disc >= 0.0) & (t > RAY_T_MIN), t, np.inf)


def _shade(normals: np.ndarray, two_sided: bool) -> np.ndarray:
    """[N] Lambert factor AMBIENT + DIFFUSE * cos for [N, 3] unit normals."""
    light = np.asarray(LIGHT_DIRECTION, float)
    cos = normals @ (light / np.linalg.norm(light))
    cos = np.abs(cos) if two_sided else np.maximum(cos, 0.0)
    return AMBIENT + DIFFUSE * cos


def render(scene: Scene, camera: PinholeCamera, c2w: np.ndarray, obj: ObjectState,
           supersample: int = 2) -> Tuple[np.ndarray, np.ndarray]:
    """Ray-cast one sharp view.

    Args:
        scene: the geometry.
        camera: intrinsics (output size camera.height x camera.width).
        c2w: [4, 4] camera-to-world, OpenGL convention.
        obj: pose of the moving sphere at this instant.
        supersample: sub-pixel samples per pixel side, averaged (box filter) for anti-aliasing.

    Returns:
        rgb: [H, W, 3] float32 linear intensity in [0, 1].
        mask: [H, W] bool, True where the moving object is the nearest hit on at least half of
            the pixel's sub-samples.
    """
    if supersample < 1:
        raise ValueError(f"render: supersample must be >= 1, got {supersample}")
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.shape != (4, 4):
        raise ValueError(f"render: c2w has shape {c2w.shape}, expected (4, 4)")
    dirs_img = camera.ray_directions(c2w, supersample)
    sh, sw = dirs_img.shape[:2]
    dirs = dirs_img.reshape(-1, 3)
    origin = c2w[:3, 3]
    n_rays = dirs.shape[0]

    stack = scene.quad_stack
    ids = np.flatnonzero(stack.facing(origin))
    t_all, a_all, b_all = _intersect_quads(stack, ids, origin, dirs.astype(np.float32))
    nearest = np.argmin(t_all, axis=1)
    rows = np.arange(n_rays)
    best_t = t_all[rows, nearest].astype(np.float64)
    best_a = a_all[rows, nearest]
    best_b = b_all[rows, nearest]
    best_id = np.where(np.isfinite(best_t), ids[nearest], -1)
    sphere_id = len(scene.quads)
    t_sphere = _intersect_sphere(obj.centre, scene.sphere.radius, origin, dirs)
    best_id[t_sphere < best_t] = sphere_id
    best_t = np.minimum(best_t, t_sphere)

    color = np.full((n_rays, 3), BACKGROUND_VALUE, dtype=np.float32)
    on_quad = (best_id >= 0) & (best_id < sphere_id)
    quad_ids = best_id[on_quad]
    albedo = scene.atlas.sample(quad_ids, best_a[on_quad], best_b[on_quad])
    color[on_quad] = albedo * scene.quad_shading[quad_ids][:, None]
    sel = best_id == sphere_id
    if np.any(sel):
        normals = (origin + best_t[sel, None] * dirs[sel] - obj.centre) / scene.sphere.radius
        local = normals @ np.asarray(obj.rotation, float)  # world -> object: R^T n, as row vectors
        lon = np.arctan2(local[:, 0], local[:, 2]) / (2.0 * np.pi) + 0.5
        lat = np.arccos(np.clip(local[:, 1], -1.0, 1.0)) / np.pi
        albedo = sample_bilinear(scene.sphere.texture, lon, lat, wrap_u=True)
        color[sel] = albedo * _shade(normals, two_sided=False)[:, None]

    s = int(supersample)
    h, w = sh // s, sw // s
    rgb = color.reshape(h, s, w, s, 3).mean(axis=(1, 3))
    coverage = (best_id == sphere_id).reshape(h, s, w, s).mean(axis=(1, 3))
    return np.clip(rgb, 0.0, 1.0).astype(np.float32), coverage >= 0.5


def to_grey(rgb: np.ndarray) -> np.ndarray:
    """[H, W] grey = 0.299 R + 0.587 G + 0.114 B of [H, W, 3] linear RGB."""
    return np.asarray(rgb, dtype=np.float64) @ np.asarray(GREY_WEIGHTS)

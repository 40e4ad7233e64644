"""The built-in synthetic 3D scene and a vectorised numpy ray caster for it.

The scene is a textured room (back wall, floor, ceiling, two side walls) holding a few static
textured boxes at different depths; ``render`` ray-casts it together with any number of posed
moving shapes (edygs_ns.sim.shapes; which ones, and how they move, is a preset's business:
edygs_ns.sim.presets). Textures come from edygs_ns.sim.appearance, deterministic from a seed.

Conventions: world units are arbitrary ("units"), y is up; the room is open behind the camera
(+z side). Cameras use the OpenGL convention of docs/layouts.md (x right, y up, looking down
-z; ``c2w`` is a 4x4 camera-to-world matrix). Rendered values are LINEAR intensity in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import List, Optional, Sequence, Tuple

import numpy as np

from edygs_ns.geometry import Intrinsics
from edygs_ns.sim.appearance import TextureAtlas, lambert, procedural_texture
from edygs_ns.sim.shapes import RAY_T_MIN, ObjectState, Shape

#: Radiance of rays that hit nothing (the open side of the room).
BACKGROUND_VALUE = 0.05
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
#: Largest number of moving objects one render can tell apart (8-bit instance ids, 0 = static).
MAX_OBJECTS = 255


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
class StaticBox:
    """The solid of one static box (its faces are quads), for keeping moving objects out of it.

    Attributes:
        centre: [3] world centre.
        rotation: [3, 3] box-to-world rotation.
        half_size: [3] half extents along the box's axes.
    """

    centre: np.ndarray
    rotation: np.ndarray
    half_size: np.ndarray

    def distance(self, points: np.ndarray) -> np.ndarray:
        """[M] Euclidean distance of [M, 3] points to the solid box (0 inside)."""
        local = (np.asarray(points, float) - self.centre) @ self.rotation
        return np.linalg.norm(np.maximum(np.abs(local) - self.half_size, 0.0), axis=-1)


@dataclass(frozen=True)
class Scene:
    """The static geometry: the room and its boxes.

    Attributes:
        quads: static textured rectangles (room and boxes).
        room_min: [3] lower corner of the room box.
        room_max: [3] upper corner of the room box.
        boxes: the static boxes as solids (their faces are among ``quads``).
    """

    quads: Tuple[Quad, ...]
    room_min: np.ndarray
    room_max: np.ndarray
    boxes: Tuple[StaticBox, ...] = ()

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
        return lambert(self.quad_stack.normals, two_sided=True).astype(np.float32)

    @property
    def room_diameter(self) -> float:
        """Diagonal of the room box in world units."""
        return float(np.linalg.norm(self.room_max - self.room_min))


class PinholeCamera(Intrinsics):
    """The simulator's camera: :class:`~edygs_ns.geometry.Intrinsics` that also casts rays."""

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


def _yawed_box(centre: np.ndarray, size: np.ndarray, yaw: float) -> StaticBox:
    """A box of full extents ``size`` rotated by ``yaw`` radians about the vertical axis."""
    c, s = np.cos(yaw), np.sin(yaw)
    return StaticBox(centre, np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]), 0.5 * size)


def _box_quads(rng: np.random.Generator, box: StaticBox) -> List[Quad]:
    """Six textured faces of ``box``."""
    ex, ey, ez = (box.rotation @ np.diag(2.0 * box.half_size)).T
    corner = box.centre - 0.5 * (ex + ey + ez)
    faces = ((corner, ex, ey), (corner + ez, ex, ey), (corner, ez, ey), (corner + ex, ez, ey), (corner, ex, ez),
             (corner + ey, ex, ez))
    return [_textured_quad(rng, origin, eu, ev, box.centre) for origin, eu, ev in faces]


def build_scene(rng: np.random.Generator) -> Scene:
    """The built-in room with its static boxes; textures and box placement come from ``rng``.

    Args:
        rng: drawn from in a fixed order (room walls, then each box); the caller may keep drawing
            from it afterwards (the moving objects' textures do).
    """
    lo, hi = np.asarray(ROOM_MIN, float), np.asarray(ROOM_MAX, float)
    quads = _room_quads(rng, lo, hi)
    boxes = []
    for cx, cz, sx, sy, sz in BOX_LAYOUT:
        jitter = rng.uniform(-BOX_JITTER, BOX_JITTER, size=2)
        centre = np.array([cx + jitter[0], lo[1] + 0.5 * sy, cz + jitter[1]])
        boxes.append(_yawed_box(centre, np.array([sx, sy, sz]), rng.uniform(-BOX_MAX_YAW, BOX_MAX_YAW)))
        quads += _box_quads(rng, boxes[-1])
    return Scene(tuple(quads), lo, hi, tuple(boxes))


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


def nearest_hits(scene: Scene, origin: np.ndarray, dirs: np.ndarray, objects: Sequence[Tuple[Shape, ObjectState]] = ()
                 ) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The nearest hit of rays from one origin among the room's quads and the posed shapes.

    Args:
        origin: [3] ray origin, world units.
        dirs: [R, 3] unit ray directions.
        objects: the moving shapes, each with its pose at this instant.

    Returns:
        t: [R] float64 distance to the hit (inf: none); ids: [R] quad index, len(scene.quads) + i
        for objects[i], -1 for none; a, b: [R] texture coordinates on the hit quad.
    """
    stack = scene.quad_stack
    ids = np.flatnonzero(stack.facing(origin))
    t_all, a_all, b_all = _intersect_quads(stack, ids, origin, dirs.astype(np.float32))
    nearest = np.argmin(t_all, axis=1)
    rows = np.arange(dirs.shape[0])
    best_t = t_all[rows, nearest].astype(np.float64)
    best_id = np.where(np.isfinite(best_t), ids[nearest], -1)
    first_object = len(scene.quads)
    for i, (shape, pose) in enumerate(objects):
        t_obj = shape.intersect(pose, origin, dirs)
        best_id[t_obj < best_t] = first_object + i
        best_t = np.minimum(best_t, t_obj)
    return best_t, best_id, a_all[rows, nearest], b_all[rows, nearest]


def render(scene: Scene, camera: PinholeCamera, c2w: np.ndarray, objects: Sequence[Tuple[Shape, ObjectState]] = (),
           supersample: int = 2) -> Tuple[np.ndarray, np.ndarray]:
    """Ray-cast one sharp view of the room and the posed moving shapes (nearest hit wins).

    Args:
        scene: the static geometry.
        camera: intrinsics (output size camera.height x camera.width).
        c2w: [4, 4] camera-to-world, OpenGL convention.
        objects: the moving shapes, each with its pose at this instant.
        supersample: sub-pixel samples per pixel side, averaged (box filter) for anti-aliasing.

    Returns:
        rgb: [H, W, 3] float32 linear intensity in [0, 1].
        instance: [H, W] uint8, 0 where static; i + 1 where the moving objects together are the
            nearest hit on at least half of the pixel's sub-samples and objects[i] on the most
            (the first such object on a tie). ``instance > 0`` is the dynamic-object mask.
    """
    if supersample < 1:
        raise ValueError(f"render: supersample must be >= 1, got {supersample}")
    if len(objects) > MAX_OBJECTS:
        raise ValueError(f"render: at most {MAX_OBJECTS} moving objects, got {len(objects)}")
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.shape != (4, 4):
        raise ValueError(f"render: c2w has shape {c2w.shape}, expected (4, 4)")
    dirs_img = camera.ray_directions(c2w, supersample)
    sh, sw = dirs_img.shape[:2]
    dirs = dirs_img.reshape(-1, 3)
    origin = c2w[:3, 3]
    n_rays = dirs.shape[0]
    best_t, best_id, best_a, best_b = nearest_hits(scene, origin, dirs, objects)
    first_object = len(scene.quads)  # best_id of objects[i] is first_object + i

    color = np.full((n_rays, 3), BACKGROUND_VALUE, dtype=np.float32)
    on_quad = (best_id >= 0) & (best_id < first_object)
    quad_ids = best_id[on_quad]
    albedo = scene.atlas.sample(quad_ids, best_a[on_quad], best_b[on_quad])
    color[on_quad] = albedo * scene.quad_shading[quad_ids][:, None]
    for i, (shape, pose) in enumerate(objects):
        sel = best_id == first_object + i
        if np.any(sel):
            color[sel] = shape.radiance(pose, origin, dirs[sel], best_t[sel])

    s = int(supersample)
    h, w = sh // s, sw // s
    rgb = color.reshape(h, s, w, s, 3).mean(axis=(1, 3))
    return np.clip(rgb, 0.0, 1.0).astype(np.float32), _instance_ids(best_id - first_object, len(objects), h, w, s)


def _instance_ids(object_index: np.ndarray, n_objects: int, h: int, w: int, s: int) -> np.ndarray:
    """[h, w] uint8 instance map from the [h*s*w*s] per-sub-sample object index (< 0: static)."""
    instance = np.zeros((h, w), dtype=np.uint8)
    if n_objects == 0:
        return instance
    coverage = (object_index >= 0).reshape(h, s, w, s).mean(axis=(1, 3))
    shares = np.stack([(object_index == i).reshape(h, s, w, s).mean(axis=(1, 3)) for i in range(n_objects)])
    winner = np.argmax(shares, axis=0).astype(np.uint8) + 1
    return np.where(coverage >= 0.5, winner, instance)


def to_grey(rgb: np.ndarray) -> np.ndarray:
    """[H, W] grey = 0.299 R + 0.587 G + 0.114 B of [H, W, 3] linear RGB."""
    return np.asarray(rgb, dtype=np.float64) @ np.asarray(GREY_WEIGHTS)

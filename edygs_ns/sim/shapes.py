"""Moving primitive shapes of the synthetic scene: a textured ellipsoid and a textured oriented box.

A shape holds its rest size and texture; where it is comes from an ``ObjectState`` (centre,
rotation and an optional per-axis scale, which deforms it). Both shapes are ray-cast in their
local frame with vectorised numpy: the ellipsoid by mapping the ray into the unit-sphere frame,
the box by the slab method. A sphere (equal radii, no scale) keeps the exact arithmetic of the
original single-sphere ray caster, so scenes rendered before the shapes existed stay identical.

Rays share one origin [3] (float64) and come as [N, 3] unit directions; ``intersect`` returns the
[N] nearest positive distance (inf on a miss) and ``radiance`` the shaded colour of given hits.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Optional, Protocol, Sequence

import numpy as np

from edygs_ns.sim.appearance import TextureAtlas, lambert, procedural_texture, sample_bilinear

#: Rays hitting closer than this are ignored (avoids self-hits at t = 0).
RAY_T_MIN = 1e-6
#: Base colour range of the moving objects' textures (saturated, so they stand out from the room).
OBJECT_BASE_RANGE = (0.1, 0.9)
#: Saturation of the moving objects' feature colours.
OBJECT_SATURATION = 1.0
#: Feature density multiplier on the moving objects' textures (they are small; make them busy).
OBJECT_DETAIL_SCALE = 3.0


@dataclass(frozen=True)
class ObjectState:
    """Pose of a moving shape at one instant.

    Attributes:
        centre: [3] world position of the shape's centre.
        rotation: [3, 3] object-to-world rotation (columns: the shape's local axes in the world).
        scale: [3] per-local-axis factor on the shape's rest size (None: rest size). A
            time-varying scale makes a non-rigid (squashing / stretching) shape.
    """

    centre: np.ndarray
    rotation: np.ndarray
    scale: Optional[np.ndarray] = None


class Shape(Protocol):
    """What the ray caster needs from a moving shape."""

    def intersect(self, pose: ObjectState, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """[N] float64 nearest ray distance > RAY_T_MIN, inf on a miss."""

    def radiance(self, pose: ObjectState, origin: np.ndarray, dirs: np.ndarray, t: np.ndarray) -> np.ndarray:
        """[M, 3] shaded linear colour at the hits ``origin + t * dirs`` ([M, 3] dirs, [M] t)."""

    def describe(self) -> Dict[str, Any]:
        """JSON-ready summary (kind and rest size; no texture)."""


def _nearest_root(half_b: np.ndarray, disc: np.ndarray, a: Any = 1.0) -> np.ndarray:
    """Nearest root > RAY_T_MIN of a t^2 + 2 half_b t + c (disc = half_b^2 - a c), inf if none."""
    root = np.sqrt(np.maximum(disc, 0.0))
    near, far = (-half_b - root) / a, (-half_b + root) / a
    t = np.where(near > RAY_T_MIN, near, far)
    return np.where((disc >= 0.0) & (t > RAY_T_MIN), t, np.inf)


def intersect_sphere(centre: np.ndarray, radius: float, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Nearest positive ray distance to the sphere (inf on a miss) for [N, 3] unit rays."""
    oc = origin - centre
    half_b = dirs @ oc
    return _nearest_root(half_b, half_b**2 - (oc @ oc - radius**2))


def _equirect(texture: np.ndarray, local: np.ndarray) -> np.ndarray:
    """[M, 3] albedo at unit local directions [M, 3] (longitude about local y, columns wrap)."""
    lon = np.arctan2(local[:, 0], local[:, 2]) / (2.0 * np.pi) + 0.5
    lat = np.arccos(np.clip(local[:, 1], -1.0, 1.0)) / np.pi
    return sample_bilinear(texture, lon, lat, wrap_u=True)


@dataclass(frozen=True)
class Ellipsoid:
    """A textured ellipsoid (a sphere when its radii are equal).

    Attributes:
        radii: [3] rest semi-axes along the local x, y, z axes, world units.
        texture: [Tv, Tu, 3] float32 linear albedo, equirectangular on the unit sphere the
            ellipsoid is mapped from (columns = longitude about local y); it stretches with it.
    """

    radii: np.ndarray
    texture: np.ndarray

    def _radii(self, pose: ObjectState) -> np.ndarray:
        return np.asarray(self.radii, float) * (1.0 if pose.scale is None else np.asarray(pose.scale, float))

    def _is_sphere(self, pose: ObjectState) -> bool:
        return pose.scale is None and bool(np.all(self.radii == self.radii[0]))

    def intersect(self, pose: ObjectState, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """[N] float64 nearest ray distance, inf on a miss (unit-sphere frame: x -> R^T (x - c) / r)."""
        if self._is_sphere(pose):
            return intersect_sphere(pose.centre, float(self.radii[0]), origin, dirs)
        radii = self._radii(pose)
        rot = np.asarray(pose.rotation, float)
        o_l = ((origin - pose.centre) @ rot) / radii
        d_l = (dirs @ rot) / radii
        a = np.einsum("nc,nc->n", d_l, d_l)
        half_b = d_l @ o_l
        return _nearest_root(half_b, half_b**2 - a * (o_l @ o_l - 1.0), a)

    def radiance(self, pose: ObjectState, origin: np.ndarray, dirs: np.ndarray, t: np.ndarray) -> np.ndarray:
        """[M, 3] textured Lambert colour at the hits."""
        rot = np.asarray(pose.rotation, float)
        if self._is_sphere(pose):
            normals = (origin + t[:, None] * dirs - pose.centre) / float(self.radii[0])
            local = normals @ rot  # world -> object: R^T n, as row vectors
            return _equirect(self.texture, local) * lambert(normals, two_sided=False)[:, None]
        radii = self._radii(pose)
        unit = ((origin + t[:, None] * dirs - pose.centre) @ rot) / radii
        unit /= np.linalg.norm(unit, axis=1, keepdims=True)
        normals = (unit / radii) @ rot.T  # gradient of |x / r|^2, back to the world
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        return _equirect(self.texture, unit) * lambert(normals, two_sided=False)[:, None]

    def describe(self) -> Dict[str, Any]:
        """{"shape": "ellipsoid", "radii": rest semi-axes}."""
        return {"shape": "ellipsoid", "radii": np.asarray(self.radii, float).tolist()}


@dataclass(frozen=True)
class Box:
    """A textured box, one texture per face.

    Attributes:
        half_size: [3] rest half extents along the local x, y, z axes, world units.
        faces: the six face textures; face 2 * axis + (1 if on the + side else 0) spans the other
            two local axes (axis + 1) % 3 (texture columns) and (axis + 2) % 3 (rows).
    """

    half_size: np.ndarray
    faces: TextureAtlas

    def _half(self, pose: ObjectState) -> np.ndarray:
        return np.asarray(self.half_size, float) * (1.0 if pose.scale is None else np.asarray(pose.scale, float))

    def intersect(self, pose: ObjectState, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """[N] float64 nearest ray distance, inf on a miss (slab method in the local frame)."""
        half = self._half(pose)
        rot = np.asarray(pose.rotation, float)
        o_l = (origin - pose.centre) @ rot
        d_l = dirs @ rot
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d_l
            t1 = (-half - o_l) * inv
            t2 = (half - o_l) * inv
        t_near = np.minimum(t1, t2).max(axis=1)
        t_far = np.maximum(t1, t2).min(axis=1)
        t = np.where(t_near > RAY_T_MIN, t_near, t_far)
        return np.where((t_far >= t_near) & (t > RAY_T_MIN), t, np.inf)

    def radiance(self, pose: ObjectState, origin: np.ndarray, dirs: np.ndarray, t: np.ndarray) -> np.ndarray:
        """[M, 3] textured Lambert colour at the hits (outward face normals)."""
        half = self._half(pose)
        rot = np.asarray(pose.rotation, float)
        local = (origin + t[:, None] * dirs - pose.centre) @ rot
        rows = np.arange(len(local))
        axis = np.argmax(np.abs(local) / half, axis=1)
        positive = local[rows, axis] > 0.0
        col_axis, row_axis = (axis + 1) % 3, (axis + 2) % 3
        a = np.clip(0.5 + local[rows, col_axis] / (2.0 * half[col_axis]), 0.0, 1.0)
        b = np.clip(0.5 + local[rows, row_axis] / (2.0 * half[row_axis]), 0.0, 1.0)
        albedo = self.faces.sample(2 * axis + positive, a, b)
        normals_l = np.zeros_like(local)
        normals_l[rows, axis] = np.where(positive, 1.0, -1.0)
        return albedo * lambert(normals_l @ rot.T, two_sided=False)[:, None]

    def describe(self) -> Dict[str, Any]:
        """{"shape": "box", "half_size": rest half extents}."""
        return {"shape": "box", "half_size": np.asarray(self.half_size, float).tolist()}


def object_texture(rng: np.random.Generator, size_u: float, size_v: float) -> np.ndarray:
    """A busy, saturated procedural texture for a moving surface of size_u x size_v world units."""
    return procedural_texture(rng, size_u, size_v, OBJECT_BASE_RANGE, OBJECT_DETAIL_SCALE, OBJECT_SATURATION)


def textured_ellipsoid(rng: np.random.Generator, radii: Sequence[float]) -> Ellipsoid:
    """An ellipsoid with semi-axes ``radii`` and an equirectangular texture drawn from ``rng``
    (sized for the largest great circle: 2 pi r_max x pi r_max)."""
    radii = np.asarray(radii, float)
    if radii.shape != (3,) or np.any(radii <= 0):
        raise ValueError(f"textured_ellipsoid: radii must be 3 positive numbers, got {radii}")
    circumference = 2.0 * np.pi * float(radii.max())
    return Ellipsoid(radii, object_texture(rng, circumference, 0.5 * circumference))


def textured_box(rng: np.random.Generator, size: Sequence[float]) -> Box:
    """A box of full extents ``size`` [3] with one texture per face drawn from ``rng``."""
    size = np.asarray(size, float)
    if size.shape != (3,) or np.any(size <= 0):
        raise ValueError(f"textured_box: size must be 3 positive numbers, got {size}")
    textures = [object_texture(rng, size[(axis + 1) % 3], size[(axis + 2) % 3]) for axis in range(3) for _ in range(2)]
    return Box(0.5 * size, TextureAtlas.from_textures(textures))


def bounding_radius(shape: Shape, pose: Optional[ObjectState] = None) -> float:
    """Radius of a sphere about the shape's centre that holds it (at ``pose``'s scale if given)."""
    scale = 1.0 if pose is None or pose.scale is None else np.asarray(pose.scale, float)
    if isinstance(shape, Ellipsoid):
        return float(np.max(np.asarray(shape.radii, float) * scale))
    if isinstance(shape, Box):
        return float(np.linalg.norm(np.asarray(shape.half_size, float) * scale))
    raise TypeError(f"bounding_radius: unknown shape {type(shape).__name__}")

"""Which pixels of a novel view the training views saw (co-visibility, true geometry).

A novel camera off the training path sees some surfaces that no training latent saw (past the
edges of every training frustum, or behind something in all of them). No reconstruction can know
them, so the evaluation also scores novel views on the co-visible pixels only (as DyCheck's
masked metrics do for monocular dynamic scenes; docs/method.md).
"""

from __future__ import annotations

from typing import Sequence, Tuple

import numpy as np

from edygs_ns.sim.scene import PinholeCamera, Scene, nearest_hits
from edygs_ns.sim.shapes import ObjectState, Shape

#: A surface point counts as seen by a training view when that view's nearest hit along the ray
#: to it lies no nearer than this fraction of the distance (occluded otherwise).
OCCLUSION_TOLERANCE = 1e-3


def covisible_counts(
    scene: Scene,
    camera: PinholeCamera,
    c2w: np.ndarray,
    objects: Sequence[Tuple[Shape, ObjectState]],
    train_c2w: Sequence[np.ndarray],
    train_objects: Sequence[Sequence[Tuple[Shape, ObjectState]]],
) -> np.ndarray:
    """For each pixel of a view, how many training views see the surface point it shows.

    Args:
        c2w: [4, 4] camera-to-world of the view (OpenGL); objects: the moving shapes posed at its instant.
        train_c2w: the training views' [4, 4] camera-to-world; train_objects: the shapes posed at each.

    Returns:
        [H, W] int32 counts (0: no training view saw it; the ray hits nothing: 0 as well).
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    dirs = camera.ray_directions(c2w, 1).reshape(-1, 3).astype(np.float64)
    t, _, _, _ = nearest_hits(scene, c2w[:3, 3], dirs, objects)
    hit = np.isfinite(t)
    points = c2w[:3, 3] + dirs * np.where(hit, t, 0.0)[:, None]
    counts = np.zeros(len(points), dtype=np.int32)
    for pose, posed in zip(train_c2w, train_objects):
        pose = np.asarray(pose, dtype=np.float64)
        local = (points - pose[:3, 3]) @ pose[:3, :3]  # camera axes, OpenGL (looking down -z)
        z = -local[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = camera.fl_x * local[:, 0] / z + camera.cx
            v = -camera.fl_y * local[:, 1] / z + camera.cy
        inside = np.flatnonzero(hit & (z > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height))
        if len(inside) == 0:
            continue
        rays = points[inside] - pose[:3, 3]
        dist = np.linalg.norm(rays, axis=1)
        t_view, _, _, _ = nearest_hits(scene, pose[:3, 3], rays / dist[:, None], posed)
        seen = t_view >= dist * (1.0 - OCCLUSION_TOLERANCE)
        counts[inside[seen]] += 1
    return counts.reshape(camera.height, camera.width)

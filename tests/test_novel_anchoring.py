"""Novel cameras placed relative to the nearest training latent (eval/pose_alignment.anchor_to_training)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from edygs_ns.eval.pose_alignment import anchor_to_training


def _pose(rotvec, centre) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    pose[:3, 3] = centre
    return pose


def test_each_novel_camera_takes_the_residual_of_the_training_latent_nearest_in_time():
    rng = np.random.default_rng(0)
    train_times = np.linspace(0.0, 1.0, 5)
    gt = np.stack([_pose(rng.normal(0, 0.1, 3), [t, 0.0, 0.0]) for t in train_times])
    # each refined pose is its ground truth turned by its own small rotation and moved by its own offset
    turns = [Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix() for _ in train_times]
    offsets = rng.normal(0, 0.02, (5, 3))
    refined = gt.copy()
    for i in range(5):
        refined[i, :3, :3] = turns[i] @ gt[i, :3, :3]
        refined[i, :3, 3] = gt[i, :3, 3] + offsets[i]
    novel = np.stack([_pose(rng.normal(0, 0.1, 3), [t, 0.2, 0.0]) for t in (0.26, 0.74)])
    anchored = anchor_to_training(novel, np.array([0.26, 0.74]), gt, refined, train_times)
    for v, nearest in enumerate((1, 3)):  # 0.26 -> 0.25, 0.74 -> 0.75
        np.testing.assert_allclose(anchored[v, :3, :3], turns[nearest] @ novel[v, :3, :3], atol=1e-12)
        np.testing.assert_allclose(anchored[v, :3, 3], novel[v, :3, 3] + offsets[nearest], atol=1e-12)
    # refined poses equal to the mapped ground truth leave the novel cameras where they are
    np.testing.assert_allclose(anchor_to_training(novel, np.array([0.26, 0.74]), gt, gt, train_times), novel, atol=1e-12)

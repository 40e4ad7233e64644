"""Tests for edygs_ns.eval.trajectory (Umeyama Sim(3), ATE, RPE, scene extent)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from edygs_ns.eval.trajectory import ate_rmse, rpe, scene_extent, trajectory_metrics
from edygs_ns.geometry import align_poses, apply_sim3, umeyama_sim3

N_POSES = 12


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: rotation by `angle` radians about unit `axis`."""
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _gt_trajectory() -> np.ndarray:
    """A helix of N_POSES camera-to-world poses, each camera turned about z and tilted."""
    poses = np.tile(np.eye(4), (N_POSES, 1, 1))
    for i in range(N_POSES):
        theta = 0.4 * i
        poses[i, :3, 3] = [math.cos(theta), math.sin(theta), 0.1 * i]
        poses[i, :3, :3] = _rotation(np.array([0.0, 0.0, 1.0]), theta) @ _rotation(np.array([1.0, 0.0, 0.0]), 0.3)
    return poses


def test_umeyama_recovers_known_sim3():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    scale, rot, trans = 2.3, _random_rotation(rng), rng.normal(size=3)
    dst = scale * src @ rot.T + trans
    s, r, t = umeyama_sim3(src, dst)
    assert s == pytest.approx(scale, abs=1e-10)
    np.testing.assert_allclose(r, rot, atol=1e-10)
    np.testing.assert_allclose(t, trans, atol=1e-10)
    assert np.linalg.det(r) == pytest.approx(1.0)
    s_fixed, _, _ = umeyama_sim3(src, dst, with_scale=False)
    assert s_fixed == 1.0


def test_umeyama_rejects_degenerate_input():
    with pytest.raises(ValueError, match="at least 3"):
        umeyama_sim3(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="coincide"):
        umeyama_sim3(np.ones((5, 3)), np.random.default_rng(1).normal(size=(5, 3)))
    with pytest.raises(ValueError, match="expected \\[N, 3\\]"):
        umeyama_sim3(np.zeros((5, 2)), np.zeros((5, 2)))


def test_align_poses_undoes_a_similarity_transform():
    gt = _gt_trajectory()
    rng = np.random.default_rng(2)
    # the estimate lives in another frame at another scale: est = Sim3^-1(gt)
    scale, rot, trans = 0.37, _random_rotation(rng), rng.normal(size=3)
    est = apply_sim3(gt, (1.0 / scale, rot.T, -(rot.T @ trans) / scale))
    aligned, (s, r, t) = align_poses(est, gt)
    np.testing.assert_allclose(aligned, gt, atol=1e-9)
    assert s == pytest.approx(scale)
    assert ate_rmse(est, gt) == pytest.approx(0.0, abs=1e-9)
    rpe_t, rpe_r = rpe(est, gt)
    assert rpe_t == pytest.approx(0.0, abs=1e-9) and rpe_r == pytest.approx(0.0, abs=1e-6)


def test_ate_grows_with_noise():
    gt = _gt_trajectory()
    rng = np.random.default_rng(3)
    direction = rng.normal(size=(N_POSES, 3))
    values = []
    for sigma in (0.0, 0.01, 0.1):
        est = gt.copy()
        est[:, :3, 3] += sigma * direction
        values.append(ate_rmse(est, gt))
    assert values[0] == pytest.approx(0.0, abs=1e-12)
    assert 0.0 < values[1] < values[2]
    # alignment can only reduce the error below the unaligned RMSE
    unaligned = math.sqrt(((0.1 * direction) ** 2).sum(axis=1).mean())
    assert values[2] <= unaligned + 1e-12


def test_rpe_constant_rotation_step_known_value():
    gt = _gt_trajectory()
    step_deg = 2.0
    est = gt.copy()
    for i in range(N_POSES):
        # turn camera i by i * step about the world z axis through its centre: centres stay put and
        # each relative rotation error is R_{i+1}^T Rz(step) R_{i+1}, an angle of exactly `step`
        est[i, :3, :3] = _rotation(np.array([0.0, 0.0, 1.0]), math.radians(step_deg * i)) @ gt[i, :3, :3]
    _, rpe_r_deg = rpe(est, gt)
    assert rpe_r_deg == pytest.approx(step_deg, abs=1e-9)
    _, rpe_r_rad = rpe(est, gt, rot_unit="rad")
    assert rpe_r_rad == pytest.approx(math.radians(step_deg), abs=1e-12)
    _, rpe_r_mean = rpe(est, gt, reduction="mean")
    assert rpe_r_mean == pytest.approx(step_deg, abs=1e-9)
    assert ate_rmse(est, gt) == pytest.approx(0.0, abs=1e-12)  # ATE sees centres only
    with pytest.raises(ValueError, match="rot_unit"):
        rpe(est, gt, rot_unit="grad")


def test_rpe_translation_known_value_for_rotating_cameras():
    # GT: identity rotations, centres on a circle in the xy plane (chord length L per step).
    # Estimate: same centres, camera i turned by i * delta about z. Alignment is the identity, and
    # pair i's error is E = [Rz(delta), (Rz(-i delta) - I) d_i], so |t_err| = 2 sin(i delta / 2) L.
    radius, step = 1.5, 0.3
    delta = math.radians(3.0)
    gt = np.tile(np.eye(4), (N_POSES, 1, 1))
    angles = step * np.arange(N_POSES)
    gt[:, 0, 3], gt[:, 1, 3] = radius * np.cos(angles), radius * np.sin(angles)
    est = gt.copy()
    for i in range(N_POSES):
        est[i, :3, :3] = _rotation(np.array([0.0, 0.0, 1.0]), i * delta)
    chord = 2.0 * radius * math.sin(step / 2.0)
    per_pair = np.array([2.0 * math.sin(i * delta / 2.0) * chord for i in range(N_POSES - 1)])
    rpe_t, rpe_r = rpe(est, gt)
    assert rpe_t == pytest.approx(math.sqrt((per_pair**2).mean()), rel=1e-9)
    assert rpe_r == pytest.approx(3.0, abs=1e-9)
    rpe_t_mean, _ = rpe(est, gt, reduction="mean")
    assert rpe_t_mean == pytest.approx(per_pair.mean(), rel=1e-9)


def test_scene_extent_and_metrics_bundle():
    gt = _gt_trajectory()
    centres = gt[:, :3, 3]
    expected = max(np.linalg.norm(a - b) for a in centres for b in centres)
    assert scene_extent(gt) == pytest.approx(expected)
    assert scene_extent(gt, extent=4.0) == 4.0
    with pytest.raises(ValueError, match="extent"):
        scene_extent(gt, extent=0.0)
    est = gt.copy()
    est[:, :3, 3] += np.random.default_rng(4).normal(scale=0.02, size=(N_POSES, 3))
    bundle = trajectory_metrics(est, gt)
    assert bundle["ate_frac"] == pytest.approx(bundle["ate"] / expected)
    assert set(bundle) == {"ate", "ate_frac", "rpe_t", "rpe_r", "extent"}


def test_pose_shape_errors_name_the_argument():
    gt = _gt_trajectory()
    with pytest.raises(ValueError, match="c2w_est"):
        ate_rmse(gt[:, :3, :], gt)
    with pytest.raises(ValueError, match="poses"):
        ate_rmse(gt[:-1], gt)

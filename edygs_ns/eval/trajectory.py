"""Camera-trajectory accuracy: ATE and RPE after Sim(3) alignment (:mod:`edygs_ns.geometry`).

Poses are camera-to-world 4x4 matrices [N, 4, 4] (any camera-axis convention, the same for the
estimate and the ground truth); everything is computed in numpy float64. Translations come out
in the ground truth's units (the estimate is scaled onto it), rotations in degrees unless
`rot_unit="rad"` is asked for.
"""

from __future__ import annotations

from typing import Dict, Literal, Optional, Tuple

import numpy as np

from edygs_ns.geometry import align_poses, check_poses, rotation_angle


def ate_rmse(c2w_est: np.ndarray, c2w_gt: np.ndarray) -> float:
    """Absolute trajectory error: RMSE of camera centres after Sim(3) alignment.

    Args:
        c2w_est: [N, 4, 4] estimated camera-to-world poses.
        c2w_gt: [N, 4, 4] ground-truth poses.

    Returns:
        sqrt(mean_i ||c_i^aligned - c_i^gt||^2) in the ground truth's units.
    """
    aligned, _ = align_poses(c2w_est, c2w_gt)
    gt = np.asarray(c2w_gt, dtype=np.float64)
    err = aligned[:, :3, 3] - gt[:, :3, 3]
    return float(np.sqrt((err**2).sum(axis=1).mean()))


def rpe(
    c2w_est: np.ndarray,
    c2w_gt: np.ndarray,
    rot_unit: Literal["deg", "rad"] = "deg",
    reduction: Literal["rmse", "mean"] = "rmse",
) -> Tuple[float, float]:
    """Relative pose error over consecutive frames, after the same Sim(3) alignment as ATE.

    For each i, the relative motions D_est = P_i^-1 P_{i+1} and D_gt likewise give the error
    E = D_gt^-1 D_est; its translation norm and rotation angle are reduced over the N - 1 pairs.

    Args:
        c2w_est: [N, 4, 4] estimated camera-to-world poses, N >= 3, in temporal order.
        c2w_gt: [N, 4, 4] ground-truth poses.
        rot_unit: "deg" (default) or "rad" for the rotational error.
        reduction: "rmse" (root mean square over pairs, default) or "mean".

    Returns:
        (rpe_trans in the ground truth's units, rpe_rot in `rot_unit`).
    """
    if rot_unit not in ("deg", "rad"):
        raise ValueError(f"rpe: rot_unit must be 'deg' or 'rad', got {rot_unit!r}")
    if reduction not in ("rmse", "mean"):
        raise ValueError(f"rpe: reduction must be 'rmse' or 'mean', got {reduction!r}")
    aligned, _ = align_poses(c2w_est, c2w_gt)
    gt = np.asarray(c2w_gt, dtype=np.float64)
    rel_est = np.linalg.inv(aligned[:-1]) @ aligned[1:]
    rel_gt = np.linalg.inv(gt[:-1]) @ gt[1:]
    err = np.linalg.inv(rel_gt) @ rel_est
    trans = np.linalg.norm(err[:, :3, 3], axis=1)
    angle = rotation_angle(err[:, :3, :3])
    if rot_unit == "deg":
        angle = np.degrees(angle)
    if reduction == "rmse":
        return float(np.sqrt((trans**2).mean())), float(np.sqrt((angle**2).mean()))
    return float(trans.mean()), float(angle.mean())


def scene_extent(c2w_gt: np.ndarray, extent: Optional[float] = None) -> float:
    """Scene size used to normalise ATE: `extent` if given, else the largest distance between
    two ground-truth camera centres (in the ground truth's units)."""
    if extent is not None:
        if not extent > 0.0:
            raise ValueError(f"scene_extent: a given extent must be > 0, got {extent}")
        return float(extent)
    centres = check_poses(c2w_gt, "c2w_gt")[:, :3, 3]
    dists = np.linalg.norm(centres[:, None, :] - centres[None, :, :], axis=-1)
    return float(dists.max())


def trajectory_metrics(
    c2w_est: np.ndarray,
    c2w_gt: np.ndarray,
    extent: Optional[float] = None,
    rot_unit: Literal["deg", "rad"] = "deg",
) -> Dict[str, float]:
    """All trajectory numbers for a metrics table.

    Returns:
        {"ate": ATE RMSE, "ate_frac": ATE / scene extent, "rpe_t": RPE translation (RMSE),
        "rpe_r": RPE rotation (RMSE, in `rot_unit`), "extent": the extent used}.
    """
    ate = ate_rmse(c2w_est, c2w_gt)
    ext = scene_extent(c2w_gt, extent)
    rpe_t, rpe_r = rpe(c2w_est, c2w_gt, rot_unit=rot_unit)
    return {"ate": ate, "ate_frac": ate / ext if ext > 0.0 else float("nan"), "rpe_t": rpe_t, "rpe_r": rpe_r, "extent": ext}

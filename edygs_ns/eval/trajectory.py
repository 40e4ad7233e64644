"""Camera-trajectory accuracy: Sim(3) (Umeyama) alignment, ATE and RPE.

Poses are camera-to-world 4x4 matrices [N, 4, 4] (any camera-axis convention, the same for the
estimate and the ground truth); everything is computed in numpy float64. Translations come out
in the ground truth's units (the estimate is scaled onto it), rotations in degrees unless
`rot_unit="rad"` is asked for.
"""

from __future__ import annotations

from typing import Dict, Literal, Optional, Tuple

import numpy as np

#: Fewest corresponding points that fix a Sim(3) (three non-collinear points).
MIN_POINTS_SIM3 = 3
#: Relative tolerance under which the source points count as all coincident (no scale defined).
DEGENERATE_VARIANCE = 1e-24
#: Pose arrays are [N, POSE_SIZE, POSE_SIZE].
POSE_SIZE = 4


def _check_points(points: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} has shape {arr.shape}, expected [N, 3]")
    return arr


def _check_poses(poses: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (POSE_SIZE, POSE_SIZE):
        raise ValueError(f"{name} has shape {arr.shape}, expected [N, 4, 4] camera-to-world matrices")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} holds non-finite values")
    return arr


def _check_pair(c2w_est: np.ndarray, c2w_gt: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    est = _check_poses(c2w_est, "c2w_est")
    gt = _check_poses(c2w_gt, "c2w_gt")
    if est.shape[0] != gt.shape[0]:
        raise ValueError(f"c2w_est has {est.shape[0]} poses but c2w_gt has {gt.shape[0]}")
    return est, gt


def umeyama_sim3(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> Tuple[float, np.ndarray, np.ndarray]:
    """Similarity transform minimising sum_i ||dst_i - (s R src_i + t)||^2 (Umeyama 1991).

    Args:
        src: [N, 3] points to be moved (e.g. estimated camera centres), N >= 3, not collinear.
        dst: [N, 3] corresponding target points (e.g. ground-truth camera centres).
        with_scale: if False, s is fixed to 1 (an SE(3) alignment).

    Returns:
        (s, R, t): scale (float > 0), rotation [3, 3] with det +1, translation [3].
    """
    src_a = _check_points(src, "src")
    dst_a = _check_points(dst, "dst")
    if src_a.shape != dst_a.shape:
        raise ValueError(f"src has shape {src_a.shape} but dst has shape {dst_a.shape}")
    n = src_a.shape[0]
    if n < MIN_POINTS_SIM3:
        raise ValueError(f"umeyama_sim3 needs at least {MIN_POINTS_SIM3} points, got {n}")
    mu_src = src_a.mean(axis=0)
    mu_dst = dst_a.mean(axis=0)
    src_c = src_a - mu_src
    dst_c = dst_a - mu_dst
    var_src = float((src_c**2).sum() / n)
    if var_src <= DEGENERATE_VARIANCE * max(1.0, float((dst_c**2).sum() / n)):
        raise ValueError("umeyama_sim3: all source points coincide, the alignment is undefined")
    cov = dst_c.T @ src_c / n  # [3, 3]
    u, d, vt = np.linalg.svd(cov)
    reflect = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        reflect[2, 2] = -1.0
    rot = u @ reflect @ vt
    scale = float(np.trace(np.diag(d) @ reflect) / var_src) if with_scale else 1.0
    trans = mu_dst - scale * rot @ mu_src
    return scale, rot, trans


def pose_sim3(src_c2w: np.ndarray, dst_c2w: np.ndarray) -> Tuple[float, np.ndarray, np.ndarray]:
    """Similarity transform taking poses ``src_c2w`` [N, 4, 4] onto ``dst_c2w`` (same order): the
    rotation from the camera orientations (the rotation R minimising sum_i ||R_dst,i - R R_src,i||²),
    then scale and translation from the centres with R fixed (least squares).

    Centres alone leave the rotation about a nearly straight or planar path undetermined: on the
    built-in scenes Umeyama's rotation was 2.6° off the one the cameras' orientations give, which
    moved every aligned novel camera by that much. Needs N >= MIN_POINTS_SIM3 poses whose centres
    do not all coincide.
    """
    src = _check_poses(src_c2w, "src_c2w")
    dst = _check_poses(dst_c2w, "dst_c2w")
    if src.shape != dst.shape:
        raise ValueError(f"src_c2w has shape {src.shape} but dst_c2w has shape {dst.shape}")
    if src.shape[0] < MIN_POINTS_SIM3:
        raise ValueError(f"pose_sim3 needs at least {MIN_POINTS_SIM3} poses, got {src.shape[0]}")
    u, _, vt = np.linalg.svd(np.einsum("nij,nkj->ik", dst[:, :3, :3], src[:, :3, :3]))
    reflect = np.eye(3)
    reflect[2, 2] = np.sign(np.linalg.det(u @ vt))
    rot = u @ reflect @ vt
    src_c = src[:, :3, 3] - src[:, :3, 3].mean(axis=0)
    dst_c = dst[:, :3, 3] - dst[:, :3, 3].mean(axis=0)
    spread = float((src_c**2).sum())
    if spread <= DEGENERATE_VARIANCE * max(1.0, float((dst_c**2).sum())):
        raise ValueError("pose_sim3: all source centres coincide, the scale is undefined")
    scale = float(np.einsum("ni,ni->", src_c @ rot.T, dst_c) / spread)
    trans = dst[:, :3, 3].mean(axis=0) - scale * rot @ src[:, :3, 3].mean(axis=0)
    return scale, rot, trans


def apply_sim3(c2w: np.ndarray, sim3: Tuple[float, np.ndarray, np.ndarray]) -> np.ndarray:
    """Move poses [N, 4, 4] by a Sim(3): centres c -> s R c + t, rotations Rc -> R Rc."""
    poses = _check_poses(c2w, "c2w")
    scale, rot, trans = sim3
    out = np.zeros_like(poses)
    out[:, :3, :3] = rot[None] @ poses[:, :3, :3]
    out[:, :3, 3] = scale * poses[:, :3, 3] @ rot.T + trans[None]
    out[:, 3, 3] = 1.0
    return out


def align_poses(
    c2w_est: np.ndarray, c2w_gt: np.ndarray, with_scale: bool = True
) -> Tuple[np.ndarray, Tuple[float, np.ndarray, np.ndarray]]:
    """Align estimated poses onto the ground truth by a Sim(3) fitted to the camera centres.

    Args:
        c2w_est: [N, 4, 4] estimated camera-to-world poses.
        c2w_gt: [N, 4, 4] ground-truth camera-to-world poses, same order.
        with_scale: fit the scale too (Sim(3)); False gives an SE(3) alignment.

    Returns:
        (aligned [N, 4, 4], (s, R [3, 3], t [3])): the estimate with centres s R c + t and
        rotations R R_c, i.e. expressed in the ground truth's frame and units.
    """
    est, gt = _check_pair(c2w_est, c2w_gt)
    sim3 = umeyama_sim3(est[:, :3, 3], gt[:, :3, 3], with_scale=with_scale)
    return apply_sim3(est, sim3), sim3


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


def rotation_angle(rot: np.ndarray) -> np.ndarray:
    """Angle in radians of rotation matrices [..., 3, 3] (in [0, pi])."""
    cos = (np.trace(rot, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


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
    centres = _check_poses(c2w_gt, "c2w_gt")[:, :3, 3]
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

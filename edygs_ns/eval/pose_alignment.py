"""Camera poses for evaluation: refined training poses, and moving ground-truth cameras into the
frame the model was trained in.

Why novel views need an alignment: the model lives in the frame of its *training* poses (given,
or from COLMAP, then refined per latent), while the ground-truth novel cameras are given in the
ground-truth frame. With COLMAP poses the two frames differ by an unknown similarity (rotation,
translation, scale); even with given poses, pose refinement may drift the whole trajectory a
little. We fit the Sim(3) that maps the ground-truth training cameras onto their refined poses —
the rotation from the cameras' orientations, scale and translation from their centres (centres
alone leave the rotation about a nearly straight path open: 2.6° off on the built-in scene) — and
apply it to the ground-truth novel cameras before rendering them. Intrinsics are unchanged. This is the standard protocol of pose-free and
pose-refining NeRF/3DGS evaluation (BARF, Nope-NeRF, CF-3DGS).

Poses are camera-to-world matrices in nerfstudio's OpenGL convention; [N, 3, 4] for `Cameras`,
[N, 4, 4] float64 numpy arrays for the trajectory maths (edygs_ns.geometry, edygs_ns.eval.trajectory).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Dict, Optional, Tuple, Union

import numpy as np
import torch
from jaxtyping import Float
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor

from edygs_ns.eval.trajectory import trajectory_metrics
from edygs_ns.geometry import MIN_POINTS_SIM3, POSE_ROWS, POSE_SIZE, Sim3, apply_sim3, pose_sim3, rotation_angle, to_homogeneous
#: Row (split) names of the pose metrics in the evaluation table.
INITIAL_POSES_SPLIT = "poses (initial)"
REFINED_POSES_SPLIT = "poses (refined)"
#: Metric keys every pose row carries (edygs_ns.eval.trajectory.trajectory_metrics).
POSE_METRIC_KEYS: Tuple[str, ...] = ("ate", "ate_frac", "rpe_t", "rpe_r", "extent")


def scale_translations(c2w: np.ndarray, factor: float) -> np.ndarray:
    """Copy of poses [N, 4, 4] with camera centres multiplied by `factor` (rotations unchanged).

    Used to undo the frame's scale so that trajectory errors come out in the ground truth's units.
    """
    out = np.array(c2w, dtype=np.float64, copy=True)
    out[:, :3, 3] *= factor
    return out


@torch.no_grad()
def refined_train_poses(model: torch.nn.Module, cameras: Cameras) -> Float[Tensor, "N 3 4"]:
    """Training poses after the model's pose refinement, [N, 3, 4] on the cameras' device.

    Uses the model's `refined_camera_to_worlds(camera)` (EdygsModel), which applies the camera
    optimiser to cameras that carry `metadata["cam_idx"]`. Models without that method, or
    without pose refinement, give the cameras' poses unchanged.

    Args:
        model: the trained model (EdygsModel).
        cameras: the N training cameras, in training-index order.

    Returns:
        [N, 3, 4] refined camera-to-world poses (OpenGL axes).
    """
    initial = cameras.camera_to_worlds
    if not hasattr(model, "refined_camera_to_worlds"):
        return initial.clone()
    device = next(model.parameters()).device
    query = Cameras(
        camera_to_worlds=initial.to(device), fx=cameras.fx.to(device), fy=cameras.fy.to(device),
        cx=cameras.cx.to(device), cy=cameras.cy.to(device), width=cameras.width.to(device),
        height=cameras.height.to(device), camera_type=cameras.camera_type.to(device),
        metadata={"cam_idx": torch.arange(cameras.shape[0], device=device)[:, None]},  # [N, 1]: per-camera field
    )
    refined = model.refined_camera_to_worlds(query)  # type: ignore[operator]
    return refined[:, :POSE_ROWS, :].to(initial.device, initial.dtype)


def fit_gt_to_model(gt_c2w: np.ndarray, model_c2w: np.ndarray) -> Tuple[Optional[Sim3], str]:
    """Sim(3) mapping ground-truth training cameras onto the model's (refined) ones: rotation from
    the camera orientations, scale and translation from the centres (``geometry.pose_sim3``).

    Args:
        gt_c2w: [N, 4, 4] ground-truth poses of the training latents.
        model_c2w: [N, 4, 4] the model's poses of the same latents, same order.

    Returns:
        (sim3, "") on success; (None, reason) when fewer than 3 poses are given or all
        ground-truth centres coincide (the similarity is then undefined).
    """
    gt = to_homogeneous(gt_c2w)
    est = to_homogeneous(model_c2w)
    if gt.shape != est.shape:
        raise ValueError(f"fit_gt_to_model: {gt.shape[0]} ground-truth poses but {est.shape[0]} model poses")
    if gt.shape[0] < MIN_POINTS_SIM3:
        return None, f"{gt.shape[0]} training poses, a Sim(3) needs at least {MIN_POINTS_SIM3}"
    try:
        return pose_sim3(gt, est), ""
    except ValueError as exc:
        return None, str(exc)


def with_poses(cameras: Cameras, c2w: Union[Tensor, np.ndarray]) -> Cameras:
    """Copy of `cameras` [N] with new camera-to-world poses ([N, 3, 4] or [N, 4, 4]); intrinsics,
    times and size kept, metadata dropped (so the model applies no pose refinement to them). A
    tensor `c2w` keeps its autograd graph (test-time pose fitting renders through it)."""
    if isinstance(c2w, Tensor):
        if c2w.dim() != 3 or c2w.shape[1:] not in ((POSE_ROWS, POSE_SIZE), (POSE_SIZE, POSE_SIZE)):
            raise ValueError(f"with_poses: poses have shape {tuple(c2w.shape)}, expected [N, 3, 4] or [N, 4, 4]")
        poses = c2w[:, :POSE_ROWS, :].to(cameras.camera_to_worlds.dtype)
    else:
        poses = torch.as_tensor(to_homogeneous(c2w)[:, :POSE_ROWS, :], dtype=cameras.camera_to_worlds.dtype)
    if poses.shape[0] != cameras.shape[0]:
        raise ValueError(f"with_poses: {poses.shape[0]} poses for {cameras.shape[0]} cameras")
    return Cameras(
        camera_to_worlds=poses.to(cameras.device), fx=cameras.fx, fy=cameras.fy, cx=cameras.cx, cy=cameras.cy,
        width=cameras.width, height=cameras.height, camera_type=cameras.camera_type,
        distortion_params=cameras.distortion_params, times=cameras.times,
    )


def align_cameras(cameras: Cameras, sim3: Optional[Sim3]) -> Cameras:
    """Move `cameras` by `sim3` (centres c -> s R c + t, rotations -> R R_c); None keeps them."""
    if sim3 is None:
        return with_poses(cameras, cameras.camera_to_worlds)
    return with_poses(cameras, apply_sim3(to_homogeneous(cameras.camera_to_worlds), sim3))


def anchor_to_training(mapped: np.ndarray, times: np.ndarray, train_mapped: np.ndarray, train_refined: np.ndarray,
                       train_times: np.ndarray) -> np.ndarray:
    """Novel cameras placed relative to the training latent nearest in time, as a user places a
    camera next to a training view: each mapped pose [V, 4, 4] gets the residual of that latent
    (its refined pose against its Sim(3)-mapped ground truth): the orientation turned by the
    residual rotation, the centre moved by the residual of the centre. No image is read.

    Args:
        mapped: [V, 4, 4] novel ground-truth poses moved by the training Sim(3); times: [V] normalised.
        train_mapped: [N, 4, 4] the training latents' ground-truth poses moved by the same Sim(3).
        train_refined: [N, 4, 4] their refined poses; train_times: [N] normalised.
    """
    mapped, train_mapped, train_refined = (to_homogeneous(p) for p in (mapped, train_mapped, train_refined))
    nearest = np.abs(np.asarray(times)[:, None] - np.asarray(train_times)[None, :]).argmin(axis=1)
    out = mapped.copy()
    ref, gt = train_refined[nearest], train_mapped[nearest]
    turn = ref[:, :3, :3] @ np.transpose(gt[:, :3, :3], (0, 2, 1))
    out[:, :3, :3] = turn @ mapped[:, :3, :3]
    out[:, :3, 3] = mapped[:, :3, 3] + ref[:, :3, 3] - gt[:, :3, 3]
    return out


@dataclass
class TrainPoses:
    """Training-latent poses [N, 4, 4] float64 in the dataparser frame, and `scale`: the length of
    one ground-truth unit in that frame (dataparser metadata "gt_units_scale")."""

    initial: np.ndarray
    refined: np.ndarray
    gt: Optional[np.ndarray]
    scale: float
    refined_note: str = ""


def pose_rows(poses: TrainPoses) -> Dict[str, Dict[str, Any]]:
    """Trajectory metrics of the initial and refined poses (POSE_METRIC_KEYS), in ground-truth units.

    A pose that cannot be scored (no ground truth, too few poses) gets the reason string for
    every key, which the report shows as "n/a".
    """
    rows: Dict[str, Dict[str, Any]] = {}
    for split, est, note in ((INITIAL_POSES_SPLIT, poses.initial, ""), (REFINED_POSES_SPLIT, poses.refined, poses.refined_note)):
        if poses.gt is None:
            rows[split] = {key: "no ground-truth poses" for key in POSE_METRIC_KEYS}
            continue
        if note:
            rows[split] = {key: note for key in POSE_METRIC_KEYS}
            continue
        unscale = 1.0 / poses.scale
        try:
            values: Dict[str, Any] = dict(trajectory_metrics(scale_translations(est, unscale), scale_translations(poses.gt, unscale)))
        except ValueError as exc:
            values = {key: str(exc) for key in POSE_METRIC_KEYS}
        values["n"] = int(est.shape[0])
        rows[split] = values
    return rows


def novel_alignment(poses: TrainPoses, enabled: bool) -> Tuple[Optional[Sim3], str]:
    """The Sim(3) ground truth -> model frame fitted on the training latents, and a note."""
    if not enabled:
        return None, "alignment disabled"
    if poses.gt is None:
        return None, "no ground-truth training poses to align with"
    sim3, reason = fit_gt_to_model(poses.gt, poses.refined)
    if sim3 is None:
        return None, f"no alignment: {reason}"
    scale, rot, trans = sim3
    angle = math.degrees(float(rotation_angle(rot)))
    return sim3, f"Sim(3) GT -> refined training poses: scale {scale:.4f}, rotation {angle:.3f} deg, |t| {np.linalg.norm(trans):.4g}"


def camera_path_json(cameras: Cameras) -> Dict[str, Any]:
    """An ``ns-render camera-path`` file that renders ``cameras`` [N] (already in the model frame,
    e.g. novel cameras moved by ``align_cameras``) one per frame, each at its own time: the true
    novel views as a user renders them, no per-view pose fitting. Field of view from fy and the
    height (the path format has no principal point: it is taken at the image centre)."""
    height, width = int(cameras.height[0, 0]), int(cameras.width[0, 0])
    path = []
    for i in range(cameras.shape[0]):
        c2w = to_homogeneous(cameras.camera_to_worlds[i : i + 1])[0]
        fov = 2.0 * math.degrees(math.atan(0.5 * height / float(cameras.fy[i, 0])))
        entry: Dict[str, Any] = {"camera_to_world": c2w.reshape(-1).tolist(), "fov": fov, "aspect": width / height}
        if cameras.times is not None:
            entry["render_time"] = float(cameras.times[i, 0])
        path.append(entry)
    return {"render_height": height, "render_width": width, "seconds": float(len(path)), "fps": 1, "camera_path": path}


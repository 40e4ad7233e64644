"""Camera geometry every package shares: intrinsics, pose conventions, pose interpolation, Sim(3).

Neutral basics (imports nothing else from edygs_ns), so the readers, the model and the evaluation
all import downward to one definition.

Conventions: poses are camera-to-world, [N, 4, 4] float64 numpy (or [C, 3|4, 4] tensors for the
torch helpers), OpenGL camera axes (x right, y up, the camera looks down -z) unless a name says
otherwise; OpenCV axes (y down, z forward) are what COLMAP and the rasterisers use.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple, Union

import numpy as np
import torch
from torch import Tensor

#: Pose arrays are [N, POSE_SIZE, POSE_SIZE] homogeneous, or [N, POSE_ROWS, POSE_SIZE] for nerfstudio's Cameras.
POSE_SIZE = 4
POSE_ROWS = 3
#: OpenGL (nerfstudio) -> OpenCV camera axes: flip y and z.
GL_TO_CV = (1.0, -1.0, -1.0)
#: The same flip as a homogeneous matrix (its own inverse: OpenCV -> OpenGL too).
OPENCV_TO_OPENGL = np.diag([*GL_TO_CV, 1.0])
#: Fewest corresponding points that fix a Sim(3) (three non-collinear points).
MIN_POINTS_SIM3 = 3
#: Relative tolerance under which the source points count as all coincident (no scale defined).
DEGENERATE_VARIANCE = 1e-24
#: A similarity transform: (scale, rotation [3, 3], translation [3]).
Sim3 = Tuple[float, np.ndarray, np.ndarray]


# ----------------------------------------------------------------------------------------------
# Intrinsics
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Intrinsics:
    """A pinhole camera without distortion (pixel centres at integer + 0.5, as COLMAP and nerfstudio).

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

    def resized(self, width: int, height: int) -> "Intrinsics":
        """The same camera for images resized to width x height pixels."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(width, height, self.fl_x * sx, self.fl_y * sy, self.cx * sx, self.cy * sy)

    def matrix(self) -> np.ndarray:
        """[3, 3] float64 calibration matrix K."""
        return np.array([[self.fl_x, 0.0, self.cx], [0.0, self.fl_y, self.cy], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------------------------
# Pose conventions
# ----------------------------------------------------------------------------------------------


def rotation_angle(rot: np.ndarray) -> np.ndarray:
    """Angle in radians of rotation matrices [..., 3, 3] (in [0, pi])."""
    cos = (np.trace(rot, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


def to_homogeneous(c2w: Union[Tensor, np.ndarray]) -> np.ndarray:
    """Camera-to-world poses [N, 3, 4] or [N, 4, 4] (tensor or array) -> float64 [N, 4, 4]."""
    arr = c2w.detach().cpu().double().numpy() if isinstance(c2w, Tensor) else np.asarray(c2w, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] not in ((POSE_ROWS, POSE_SIZE), (POSE_SIZE, POSE_SIZE)):
        raise ValueError(f"poses have shape {arr.shape}, expected [N, 3, 4] or [N, 4, 4] camera-to-world matrices")
    out = np.zeros((arr.shape[0], POSE_SIZE, POSE_SIZE))
    out[:, :POSE_ROWS, :] = arr[:, :POSE_ROWS, :]
    out[:, POSE_ROWS, POSE_ROWS] = 1.0
    return out


def llff_to_opengl(poses: np.ndarray) -> np.ndarray:
    """LLFF 3x5 poses [N, 3, 5] (columns down, right, back, t, hwf) to OpenGL c2w [N, 4, 4]."""
    out = np.zeros((len(poses), POSE_SIZE, POSE_SIZE), dtype=np.float64)
    out[:, :3, 0] = poses[:, :, 1]
    out[:, :3, 1] = -poses[:, :, 0]
    out[:, :3, 2] = poses[:, :, 2]
    out[:, :3, 3] = poses[:, :, 3]
    out[:, 3, 3] = 1.0
    return out


def colmap_w2c_to_c2w_opengl(w2c_3x4: np.ndarray) -> np.ndarray:
    """COLMAP world-to-camera [3, 4] (OpenCV axes) -> camera-to-world [4, 4] (OpenGL axes)."""
    w2c = np.eye(4)
    w2c[:3, :4] = w2c_3x4
    return np.linalg.inv(w2c) @ OPENCV_TO_OPENGL


def c2w_opengl_to_colmap_w2c(c2w: np.ndarray) -> np.ndarray:
    """Inverse of :func:`colmap_w2c_to_c2w_opengl`: [4, 4] c2w (OpenGL) -> [3, 4] w2c (OpenCV)."""
    return np.linalg.inv(np.asarray(c2w, dtype=np.float64) @ OPENCV_TO_OPENGL)[:3, :4]


def adjust_poses(c2w: Tensor, adj: Tensor) -> Tensor:
    """Apply SE(3) corrections [C, 3, 4] to poses [C, 3, 4] as nerfstudio's camera optimiser
    does: rotation R' = R_adj R, centre t' = t + t_adj."""
    return torch.cat([torch.bmm(adj[:, :3, :3], c2w[:, :3, :3]), c2w[:, :3, 3:] + adj[:, :3, 3:]], dim=-1)


def _bottom_row(like: Tensor) -> Tensor:
    """[C, 1, 4] rows (0, 0, 0, 1) on ``like``'s device, made there (no upload of host data)."""
    bottom = like.new_zeros(like.shape[0], 1, 4)
    bottom[..., 3].fill_(1.0)
    return bottom


def c2w_opencv(c2w: Tensor) -> Tensor:
    """[C, 3|4, 4] camera-to-world (OpenGL axes) -> [C, 4, 4] camera-to-world (OpenCV axes)."""
    rot = c2w[:, :3, :3]
    flipped = torch.cat([rot[..., :1], -rot[..., 1:3]], dim=-1)  # columns times GL_TO_CV = (1, -1, -1)
    return torch.cat([torch.cat([flipped, c2w[:, :3, 3:4]], dim=-1), _bottom_row(c2w)], dim=1)


def viewmats_from_c2w(c2w: Tensor) -> Tensor:
    """[C, 3|4, 4] camera-to-world (OpenGL axes) -> [C, 4, 4] world-to-camera (OpenCV axes)."""
    cv = c2w_opencv(c2w)
    rot, trans = cv[:, :3, :3], cv[:, :3, 3:4]
    rot_inv = rot.transpose(1, 2)
    top = torch.cat([rot_inv, -rot_inv @ trans], dim=-1)
    return torch.cat([top, _bottom_row(c2w)], dim=1)


def camera_centres(viewmats: Tensor) -> Tensor:
    """[C, 3] world positions of the cameras of [C, 4, 4] world-to-camera matrices (-Rᵀ t)."""
    return -torch.einsum("nji,nj->ni", viewmats[:, :3, :3], viewmats[:, :3, 3])


# ----------------------------------------------------------------------------------------------
# Pose interpolation
# ----------------------------------------------------------------------------------------------


#: Fewest known instants for cubic interpolation of translations (a not-a-knot cubic spline,
#: as scipy's interp1d(kind="cubic")); with fewer, translations are interpolated linearly.
CUBIC_MIN_POINTS = 4


def interpolate_poses(
    times: np.ndarray, c2w: np.ndarray, query: np.ndarray, translation: str = "linear"
) -> np.ndarray:
    """Poses at query times: rotations slerped, centres linear or cubic; clamped outside the known times.

    Args:
        times: [M] strictly increasing µs.
        c2w: [M, 4, 4] poses at those times.
        query: [Q] µs.
        translation: "linear" (piecewise linear centres) or "cubic" (a not-a-knot cubic spline
            through the centres, what scipy's ``interp1d(kind="cubic")`` gives, as EvDeblurNeRF
            interpolates its camera path; linear when fewer than CUBIC_MIN_POINTS are known).

    Returns:
        [Q, 4, 4] float64.

    Raises:
        ValueError: an unknown ``translation``.
    """
    from scipy.interpolate import CubicSpline
    from scipy.spatial.transform import Rotation, Slerp

    if translation not in ("linear", "cubic"):
        raise ValueError(f"interpolate_poses: translation must be 'linear' or 'cubic', got {translation!r}")
    known = np.asarray(times, dtype=np.float64)
    q = np.clip(np.asarray(query, dtype=np.float64), known[0], known[-1])
    out = np.tile(np.eye(4), (len(q), 1, 1))
    if len(known) == 1:
        out[:] = c2w[0]
        return out
    out[:, :3, :3] = Slerp(known, Rotation.from_matrix(c2w[:, :3, :3]))(q).as_matrix()
    if translation == "cubic" and len(known) >= CUBIC_MIN_POINTS:
        out[:, :3, 3] = CubicSpline(known, c2w[:, :3, 3], axis=0, bc_type="not-a-knot")(q)
    else:
        for axis in range(3):
            out[:, axis, 3] = np.interp(q, known, c2w[:, axis, 3])
    return out


# ----------------------------------------------------------------------------------------------
# Sim(3) alignment
# ----------------------------------------------------------------------------------------------


def check_points(points: np.ndarray, name: str) -> np.ndarray:
    """``points`` as float64 [N, 3]; ValueError naming ``name`` otherwise."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} has shape {arr.shape}, expected [N, 3]")
    return arr


def check_poses(poses: np.ndarray, name: str) -> np.ndarray:
    """``poses`` as finite float64 [N, 4, 4]; ValueError naming ``name`` otherwise."""
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (POSE_SIZE, POSE_SIZE):
        raise ValueError(f"{name} has shape {arr.shape}, expected [N, 4, 4] camera-to-world matrices")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} holds non-finite values")
    return arr


def check_pose_pair(c2w_est: np.ndarray, c2w_gt: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Both pose sets checked by :func:`check_poses`, and of equal length."""
    est = check_poses(c2w_est, "c2w_est")
    gt = check_poses(c2w_gt, "c2w_gt")
    if est.shape[0] != gt.shape[0]:
        raise ValueError(f"c2w_est has {est.shape[0]} poses but c2w_gt has {gt.shape[0]}")
    return est, gt


def umeyama_sim3(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> Sim3:
    """Similarity transform minimising sum_i ||dst_i - (s R src_i + t)||^2 (Umeyama 1991).

    Args:
        src: [N, 3] points to be moved (e.g. estimated camera centres), N >= 3, not collinear.
        dst: [N, 3] corresponding target points (e.g. ground-truth camera centres).
        with_scale: if False, s is fixed to 1 (an SE(3) alignment).

    Returns:
        (s, R, t): scale (float > 0), rotation [3, 3] with det +1, translation [3].
    """
    src_a = check_points(src, "src")
    dst_a = check_points(dst, "dst")
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


def pose_sim3(src_c2w: np.ndarray, dst_c2w: np.ndarray) -> Sim3:
    """Similarity transform taking poses ``src_c2w`` [N, 4, 4] onto ``dst_c2w`` (same order): the
    rotation from the camera orientations (the rotation R minimising sum_i ||R_dst,i - R R_src,i||²),
    then scale and translation from the centres with R fixed (least squares).

    Centres alone leave the rotation about a nearly straight or planar path undetermined: on the
    built-in scenes Umeyama's rotation was 2.6° off the one the cameras' orientations give, which
    moved every aligned novel camera by that much. Needs N >= MIN_POINTS_SIM3 poses whose centres
    do not all coincide.
    """
    src = check_poses(src_c2w, "src_c2w")
    dst = check_poses(dst_c2w, "dst_c2w")
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


def apply_sim3(c2w: np.ndarray, sim3: Sim3) -> np.ndarray:
    """Move poses [N, 4, 4] by a Sim(3): centres c -> s R c + t, rotations Rc -> R Rc."""
    poses = check_poses(c2w, "c2w")
    scale, rot, trans = sim3
    out = np.zeros_like(poses)
    out[:, :3, :3] = rot[None] @ poses[:, :3, :3]
    out[:, :3, 3] = scale * poses[:, :3, 3] @ rot.T + trans[None]
    out[:, 3, 3] = 1.0
    return out


def align_poses(
    c2w_est: np.ndarray, c2w_gt: np.ndarray, with_scale: bool = True
) -> Tuple[np.ndarray, Sim3]:
    """Align estimated poses onto the ground truth by a Sim(3) fitted to the camera centres.

    Args:
        c2w_est: [N, 4, 4] estimated camera-to-world poses.
        c2w_gt: [N, 4, 4] ground-truth camera-to-world poses, same order.
        with_scale: fit the scale too (Sim(3)); False gives an SE(3) alignment.

    Returns:
        (aligned [N, 4, 4], (s, R [3, 3], t [3])): the estimate with centres s R c + t and
        rotations R R_c, i.e. expressed in the ground truth's frame and units.
    """
    est, gt = check_pose_pair(c2w_est, c2w_gt)
    sim3 = umeyama_sim3(est[:, :3, 3], gt[:, :3, 3], with_scale=with_scale)
    return apply_sim3(est, sim3), sim3

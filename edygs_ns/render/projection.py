"""EWA projection of 3D Gaussians to screen space, in pure PyTorch (any device, any float dtype).

This is the projection step of gsplat 1.4.0's ``fully_fused_projection`` (pinhole camera,
"classic" rasterize mode) written with differentiable torch operations, so gradients reach
means, quaternions, scales *and* the world-to-camera matrices. Shapes: N Gaussians, C cameras.
Cameras use the OpenCV convention (x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float, Int
from torch import Tensor

from edygs_ns.render.contract import DEFAULT_FAR, DEFAULT_NEAR, LOW_PASS_EPS

#: screen radius in standard deviations of the major axis (gsplat: 3 sigma).
RADIUS_SIGMAS = 3.0
#: lower bound of the eigenvalue discriminant b^2 - det when computing the radius (gsplat).
MIN_DISCRIMINANT = 0.01
#: guard band, as a fraction of the half field of view, beyond which the Jacobian of the
#: projection is evaluated at the clamped position (gsplat's persp_proj).
FOV_GUARD_BAND = 0.3


@dataclass
class Projection:
    """Screen-space Gaussians for C cameras.

    Attributes:
        means2d: [C, N, 2] centres in pixels (x right, y down); differentiable.
        conics: [C, N, 3] inverse 2D covariance (a, b, c) = [[a, b], [b, c]] in 1/pixel^2,
            including the low-pass filter; differentiable.
        depths: [C, N] camera-space z in world units; differentiable.
        radii: [C, N] int32 screen radius in pixels, 0 where culled (not differentiable).
    """

    means2d: Float[Tensor, "C N 2"]
    conics: Float[Tensor, "C N 3"]
    depths: Float[Tensor, "C N"]
    radii: Int[Tensor, "C N"]


def quat_to_rotmat(quats: Float[Tensor, "N 4"]) -> Float[Tensor, "N 3 3"]:
    """Rotation matrices from (not necessarily unit) quaternions in wxyz order."""
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))


def covariance_3d(quats: Float[Tensor, "N 4"], scales: Float[Tensor, "N 3"]) -> Float[Tensor, "N 3 3"]:
    """World covariance R diag(s)^2 R^T of each Gaussian (scales are standard deviations)."""
    m = quat_to_rotmat(quats) * scales[:, None, :]
    return m @ m.transpose(-1, -2)


def project_gaussians(
    means: Float[Tensor, "N 3"],
    quats: Float[Tensor, "N 4"],
    scales: Float[Tensor, "N 3"],
    viewmats: Float[Tensor, "C 4 4"],
    Ks: Float[Tensor, "C 3 3"],
    width: int,
    height: int,
    near_plane: float = DEFAULT_NEAR,
    far_plane: float = DEFAULT_FAR,
    eps2d: float = LOW_PASS_EPS,
) -> Projection:
    """Project Gaussians through C pinhole cameras, with gsplat's culling rules.

    A Gaussian is culled (radius 0) when its depth is outside [near_plane, far_plane], when its
    2D covariance (after adding ``eps2d`` pixels^2 to the diagonal, the low-pass filter) is not
    positive definite, or when its 3-sigma square lies entirely off the image.

    Args:
        means: [N, 3] world positions.
        quats: [N, 4] wxyz rotations, need not be normalised.
        scales: [N, 3] positive standard deviations in world units.
        viewmats: [C, 4, 4] world-to-camera (OpenCV).
        Ks: [C, 3, 3] pixel intrinsics.
        width, height: image size in pixels.
        near_plane, far_plane: depth range in world units.
        eps2d: low-pass filter variance in pixels^2.

    Returns:
        The screen-space Gaussians; culled entries have finite (meaningless) values.
    """
    rot_view = viewmats[:, :3, :3]  # [C, 3, 3]
    trans_view = viewmats[:, :3, 3]  # [C, 3]
    means_c = torch.matmul(means, rot_view.transpose(1, 2)) + trans_view[:, None, :]  # [C, N, 3]
    x, y, z = means_c.unbind(-1)
    in_range = (z >= near_plane) & (z <= far_plane)
    z_safe = torch.where(in_range, z, torch.ones_like(z))

    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]  # [C, 1]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    inv_z = 1.0 / z_safe
    means2d = torch.stack([fx * x * inv_z + cx, fy * y * inv_z + cy], dim=-1)  # [C, N, 2]

    # the Jacobian is evaluated at the position clamped to a guard band around the frustum
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + FOV_GUARD_BAND * tan_fovx
    lim_x_neg = cx / fx + FOV_GUARD_BAND * tan_fovx
    lim_y_pos = (height - cy) / fy + FOV_GUARD_BAND * tan_fovy
    lim_y_neg = cy / fy + FOV_GUARD_BAND * tan_fovy
    tx = z_safe * torch.minimum(lim_x_pos, torch.maximum(-lim_x_neg, x * inv_z))
    ty = z_safe * torch.minimum(lim_y_pos, torch.maximum(-lim_y_neg, y * inv_z))
    j00, j02 = fx * inv_z, -fx * tx * inv_z * inv_z  # J = [[j00, 0, j02], [0, j11, j12]]
    j11, j12 = fy * inv_z, -fy * ty * inv_z * inv_z

    # camera-space square root of the covariance: M = R_view R_gauss diag(s), cov_c = M M^T
    m_world = quat_to_rotmat(quats) * scales[:, None, :]  # [N, 3, 3]
    n = means.shape[0]
    m_cam = torch.matmul(rot_view, m_world.permute(1, 0, 2).reshape(3, 3 * n)).view(-1, 3, n, 3)  # [C, i, N, k]
    row0 = j00[..., None] * m_cam[:, 0] + j02[..., None] * m_cam[:, 2]  # [C, N, 3]
    row1 = j11[..., None] * m_cam[:, 1] + j12[..., None] * m_cam[:, 2]
    cov_a = (row0 * row0).sum(-1) + eps2d
    cov_b = (row0 * row1).sum(-1)
    cov_c = (row1 * row1).sum(-1) + eps2d
    det = cov_a * cov_c - cov_b * cov_b
    valid = in_range & (det > 0)
    det_safe = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([cov_c / det_safe, -cov_b / det_safe, cov_a / det_safe], dim=-1)

    with torch.no_grad():
        half_trace = 0.5 * (cov_a + cov_c)
        major = half_trace + torch.sqrt(torch.clamp(half_trace * half_trace - det, min=MIN_DISCRIMINANT))
        radius = torch.ceil(RADIUS_SIGMAS * torch.sqrt(major))
        mx, my = means2d[..., 0], means2d[..., 1]
        on_screen = (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
        keep = valid & on_screen & (radius > 0)
        radii = torch.where(keep, radius, torch.zeros_like(radius)).to(torch.int32)
    return Projection(means2d=means2d, conics=conics, depths=z, radii=radii)

"""View-dependent colour from spherical harmonics, in the 3DGS / gsplat sign convention.

Pure torch so that both rasteriser backends get the same evaluated colours, and so that
``ns-export gaussian-splat`` writes coefficients that standard 3DGS viewers read correctly.
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525251999, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
    -0.4570457994644658, 1.445305721320277, -0.5900435899266435,
)
MAX_SH_DEGREE = 3
#: colours are offset by 0.5 so that zero coefficients mean mid-grey (3DGS convention).
SH_OFFSET = 0.5


def sh_basis(degree: int, dirs: Float[Tensor, "N 3"]) -> Float[Tensor, "N K"]:
    """The (degree + 1)^2 real SH basis values at unit directions."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh_basis: degree must be in [0, {MAX_SH_DEGREE}], got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def sh_to_rgb(
    coeffs: Float[Tensor, "N K 3"], means: Float[Tensor, "N 3"], camera_center: Float[Tensor, "3"], degree: int
) -> Float[Tensor, "N 3"]:
    """Colour seen from ``camera_center``, using the first (degree + 1)^2 coefficients, clamped at 0."""
    k = (degree + 1) ** 2
    if coeffs.shape[1] < k:
        raise ValueError(f"sh_to_rgb: {coeffs.shape[1]} coefficients cannot give degree {degree}")
    if degree == 0:
        rgb = SH_C0 * coeffs[:, 0]
    else:
        dirs = torch.nn.functional.normalize(means.detach() - camera_center, dim=-1)
        rgb = (sh_basis(degree, dirs)[:, :, None] * coeffs[:, :k]).sum(dim=1)
    return torch.relu(rgb + SH_OFFSET)

"""The per-Gaussian attribute set of EDyGS and its initialisation.

One tuple of names, ``GAUSSIAN_ATTRIBUTES``, drives the parameter groups, the optimizer configs,
checkpoint resizing and densification (gsplat's ops resize every tensor of the dict together).
"""

from __future__ import annotations

import math
from typing import Dict, Optional, Tuple

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor, nn

from edygs_ns.model.appearance import SH_C0, SH_OFFSET
from edygs_ns.io.images import UINT8_MAX

#: the motion-mask logit of each Gaussian (its own parameter group: it trains from the static phase).
MASK_ATTRIBUTE = "mask_logit"
#: every per-Gaussian tensor; the mask logit is densified with its Gaussian like the others.
GAUSSIAN_ATTRIBUTES: Tuple[str, ...] = (
    "means", "scales", "quats", "features_dc", "features_rest", "opacities", MASK_ATTRIBUTE,
)
#: neighbours used for the initial scale (mean distance), as in 3DGS.
INIT_NEIGHBOURS = 3
#: smallest initial scale, guards duplicated points.
MIN_INIT_SCALE = 1e-4


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def rgb_to_sh(rgb: Tensor) -> Tensor:
    return (rgb - SH_OFFSET) / SH_C0


def logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def knn_mean_distance(points: Float[Tensor, "N 3"], k: int = INIT_NEIGHBOURS) -> Float[Tensor, "N"]:
    """Mean distance of every point to its k nearest neighbours (sklearn KD-tree on CPU)."""
    from sklearn.neighbors import NearestNeighbors

    x = points.detach().cpu().numpy()
    n_neighbors = min(k + 1, len(x))
    if n_neighbors < 2:
        return torch.full((len(x),), 0.01)
    dist, _ = NearestNeighbors(n_neighbors=n_neighbors).fit(x).kneighbors(x)
    return torch.from_numpy(dist[:, 1:].mean(axis=1).astype(np.float32))


def random_unit_quats(n: int, generator: Optional[torch.Generator] = None) -> Float[Tensor, "N 4"]:
    """Uniformly random rotations as unit quaternions (wxyz)."""
    u = torch.rand(n, 3, generator=generator)
    a, b, c = u[:, 0], 2 * math.pi * u[:, 1], 2 * math.pi * u[:, 2]
    return torch.stack(
        [torch.sqrt(1 - a) * torch.sin(b), torch.sqrt(1 - a) * torch.cos(b), torch.sqrt(a) * torch.sin(c), torch.sqrt(a) * torch.cos(c)],
        dim=-1,
    )


def gaussian_tensors(
    points: Float[Tensor, "N 3"],
    rgb: Float[Tensor, "N 3"],
    radii: Float[Tensor, "N"],
    quats: Float[Tensor, "N 4"],
    sh_degree: int,
    opacity: float,
    mask: float,
) -> Dict[str, Tensor]:
    """Raw attribute tensors, one per GAUSSIAN_ATTRIBUTES name: Gaussians at ``points`` with RGB in
    [0, 1] (SH degree 0; higher bands zero), isotropic world ``radii``, the given opacity and mask m."""
    n = points.shape[0]
    features = torch.zeros(n, num_sh_bases(sh_degree), 3, device=points.device)
    features[:, 0] = rgb_to_sh(rgb.float())
    return {
        "means": points.float().clone(),
        "scales": torch.log(radii.float().clamp_min(MIN_INIT_SCALE))[:, None].repeat(1, 3),
        "quats": quats.float(),
        "features_dc": features[:, 0].contiguous(),
        "features_rest": features[:, 1:].contiguous(),
        "opacities": torch.full((n, 1), logit(opacity), device=points.device),
        MASK_ATTRIBUTE: torch.full((n, 1), logit(mask), device=points.device),
    }


def init_gaussians(
    points: Float[Tensor, "N 3"],
    colors: Optional[Tensor],
    sh_degree: int,
    init_opacity: float,
    init_mask: float,
    seed: int = 0,
) -> nn.ParameterDict:
    """Gaussians at ``points`` with colours (uint8 [N,3] or float in [0,1]; random when missing),
    the 3DGS initial scale (mean distance to the nearest points), random rotations and mask m = init_mask."""
    n = points.shape[0]
    generator = torch.Generator().manual_seed(seed)
    if colors is not None and len(colors) == n:
        rgb = colors.float() / UINT8_MAX if colors.dtype == torch.uint8 else colors.float()
    else:
        rgb = torch.rand(n, 3, generator=generator)
    quats = random_unit_quats(n, generator)
    params = gaussian_tensors(points, rgb, knn_mean_distance(points), quats, sh_degree, init_opacity, init_mask)
    return nn.ParameterDict({name: nn.Parameter(params[name]) for name in GAUSSIAN_ATTRIBUTES})


def seed_tensors(
    points: Float[Tensor, "S 3"],
    colors: Float[Tensor, "S 3"],
    radii: Float[Tensor, "S"],
    sh_degree: int,
    opacity: float,
    mask: float,
) -> Dict[str, Tensor]:
    """Raw attribute tensors of isotropic, unrotated Gaussians (dynamic seeds) at ``points``."""
    quats = torch.zeros(points.shape[0], 4, device=points.device)
    quats[:, 0] = 1.0
    return gaussian_tensors(points, colors, radii, quats, sh_degree, opacity, mask)

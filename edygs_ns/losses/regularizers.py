"""Mask and motion regularisers of EDyGS (paper Eq. 4, 6-8)."""

from __future__ import annotations

from typing import Optional

import torch
from jaxtyping import Float
from torch import Tensor


def mask_l1(mask: Float[Tensor, "*B H W 1"]) -> Tensor:
    """‖M‖₁ (mean): biases the rendered motion mask towards static (Eq. 4)."""
    return mask.abs().mean()


def mask_consistency(mask: Float[Tensor, "*B H W 1"], reference: Float[Tensor, "*B H W 1"]) -> Tensor:
    """‖M − M̂‖₁ (mean) against the targets M̂ fixed at the static -> dynamic switch (Eq. 8: the
    paper's M̂ is the mask rendered by the static model; by default ours is the motion evidence
    near the moving objects, docs/method.md D6)."""
    if mask.shape != reference.shape:
        raise ValueError(f"mask_consistency: mask {tuple(mask.shape)} vs reference {tuple(reference.shape)}")
    return (mask - reference.detach()).abs().mean()


def motion_loss(
    d_xyz: Float[Tensor, "N 3"],
    d_rot: Float[Tensor, "N 4"],
    d_scale: Float[Tensor, "N 3"],
    mask: Float[Tensor, "N"],
    weight: Optional[Float[Tensor, "N"]] = None,
) -> Tensor:
    """‖(1−m)Δμ‖² + ‖(1−m)Δr‖² + ‖(1−m)Δs‖², averaged over Gaussians (Eq. 6-7).

    Args:
        mask: per-Gaussian dynamic probability m in [0, 1].
        weight: 1 for the Gaussians that count, 0 for the others (the masked deformation's
            subset); the mean is over those that count (0 when none do). None: all count.
    """
    if d_xyz.shape[0] == 0:
        return d_xyz.sum()
    static = (1.0 - mask)[:, None]
    total = (static * d_xyz).square().sum(-1) + (static * d_rot).square().sum(-1) + (static * d_scale).square().sum(-1)
    if weight is None:
        return total.mean()
    return (total * weight).sum() / weight.sum().clamp_min(1.0)

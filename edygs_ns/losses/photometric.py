"""Photometric loss of 3DGS: L = (1 - λ) L1 + λ (1 - SSIM), 11x11 Gaussian window, σ = 1.5."""

from __future__ import annotations

from typing import Optional

import torch
from jaxtyping import Float
from pytorch_msssim import ssim
from torch import Tensor

#: SSIM window of 3DGS and the paper.
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5


def _to_nchw(image: Tensor) -> Tensor:
    """[..., H, W, C] -> [B, C, H, W]."""
    if image.dim() == 3:
        image = image[None]
    return image.permute(0, 3, 1, 2)


def dssim(pred: Float[Tensor, "*B H W C"], target: Float[Tensor, "*B H W C"]) -> Tensor:
    """1 - SSIM, averaged over the batch (images in [0, 1])."""
    value = ssim(_to_nchw(pred), _to_nchw(target), data_range=1.0, size_average=True,
                 win_size=SSIM_WINDOW, win_sigma=SSIM_SIGMA)
    return 1.0 - value


def l1_dssim(
    pred: Float[Tensor, "*B H W C"],
    target: Float[Tensor, "*B H W C"],
    ssim_lambda: float,
    weight: Optional[Float[Tensor, "*B H W 1"]] = None,
) -> Tensor:
    """(1 - λ)·L1 + λ·D-SSIM. ``weight`` multiplies both images first (the paper's (1 - M) term)."""
    if pred.shape != target.shape:
        raise ValueError(f"l1_dssim: pred {tuple(pred.shape)} and target {tuple(target.shape)} differ")
    if weight is not None:
        pred = pred * weight
        target = target * weight
    l1 = (pred - target).abs().mean()
    if ssim_lambda == 0.0:
        return l1
    return (1.0 - ssim_lambda) * l1 + ssim_lambda * dssim(pred, target)

"""Image metrics: PSNR, SSIM and motion-mask IoU (the model logs them, edygs-eval reports them).

Images are float tensors in [0, 1], shaped [H, W, 3] or [B, H, W, 3] (channels last, as
nerfstudio renders them). The device is taken from the tensors. Every metric returns a Python
float averaged over the batch (each image weighs the same).
"""

from __future__ import annotations

import math
from typing import Literal, Optional

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float
from torch import Tensor

#: Peak value of the images (they live in [0, 1]).
DATA_RANGE = 1.0
#: SSIM Gaussian window: side length in pixels and standard deviation in pixels (Wang et al. 2004).
SSIM_WINDOW_SIZE = 11
SSIM_SIGMA = 1.5
#: SSIM stabilising constants, C1 = (K1 * L)^2, C2 = (K2 * L)^2 with L = DATA_RANGE.
SSIM_K1 = 0.01
SSIM_K2 = 0.03
#: Number of colour channels expected in the last axis.
NUM_CHANNELS = 3
#: SSIM border handling: "valid" (window only where it fits, Wang et al.'s reference; default),
#: "reflect" (reflect-padded 'same' output, torchmetrics >= 1.x and so nerfstudio's ns-eval),
#: "zero" (zero-padded 'same' output, the original 3DGS code and its descendants' metric scripts).
SsimPadding = Literal["valid", "reflect", "zero"]
SSIM_DEFAULT_PADDING: SsimPadding = "zero"
#: IoU reported when both the predicted and the ground-truth masks are empty.
EMPTY_UNION_IOU = 1.0


def _as_batch(image: Tensor, name: str) -> Tensor:
    """Return `image` as [B, H, W, 3], raising ValueError on any other shape."""
    if image.dim() == 3:
        image = image.unsqueeze(0)
    if image.dim() != 4 or image.shape[-1] != NUM_CHANNELS:
        raise ValueError(f"{name} has shape {tuple(image.shape)}, expected [H, W, 3] or [B, H, W, 3]")
    return image


def _check_pair(pred: Tensor, gt: Tensor) -> tuple[Tensor, Tensor]:
    """Batch both images and check that their shapes agree."""
    pred_b, gt_b = _as_batch(pred, "pred"), _as_batch(gt, "gt")
    if pred_b.shape != gt_b.shape:
        raise ValueError(f"pred has shape {tuple(pred.shape)} but gt has shape {tuple(gt.shape)}")
    return pred_b, gt_b.to(device=pred_b.device, dtype=pred_b.dtype)


def psnr(
    pred: Float[Tensor, "*B H W 3"],
    gt: Float[Tensor, "*B H W 3"],
    mask: Optional[Tensor] = None,
) -> float:
    """Peak signal-to-noise ratio in dB, averaged over the images of the batch.

    PSNR = 10 log10(DATA_RANGE^2 / MSE), the MSE taken over all pixels and channels of one image
    (or over the pixels where `mask` is true). Identical images give `math.inf`.

    Args:
        pred: [H, W, 3] or [B, H, W, 3] prediction in [0, 1].
        gt: same shape as `pred`, ground truth in [0, 1].
        mask: optional [H, W] or [B, H, W] (bool, or float weights in [0, 1]) selecting the
            pixels that count; each image needs at least one selected pixel.

    Returns:
        Mean PSNR over the batch in dB (inf if any image is reproduced exactly).
    """
    pred_b, gt_b = _check_pair(pred, gt)
    squared = (pred_b - gt_b).pow(2).mean(dim=-1)  # [B, H, W]
    if mask is None:
        mse = squared.flatten(1).mean(dim=1)
    else:
        weights = mask.to(device=squared.device, dtype=squared.dtype)
        if weights.dim() == 2:
            weights = weights.unsqueeze(0)
        if weights.shape[-2:] != squared.shape[-2:] or weights.shape[0] not in (1, squared.shape[0]):
            raise ValueError(f"mask has shape {tuple(mask.shape)}, expected [H, W] or [B, H, W] matching {tuple(pred.shape)}")
        weights = weights.expand_as(squared)
        total = weights.flatten(1).sum(dim=1)
        if bool((total <= 0).any()):
            raise ValueError("psnr: mask selects no pixel in at least one image")
        mse = (squared * weights).flatten(1).sum(dim=1) / total
    values = [math.inf if m == 0.0 else 10.0 * math.log10(DATA_RANGE**2 / m) for m in mse.tolist()]
    return float(sum(values) / len(values))


def gaussian_window(size: int = SSIM_WINDOW_SIZE, sigma: float = SSIM_SIGMA, device: Optional[torch.device] = None,
                    dtype: torch.dtype = torch.float32) -> Float[Tensor, "size size"]:
    """Normalised 2D Gaussian window [size, size] with standard deviation `sigma` pixels."""
    offsets = torch.arange(size, device=device, dtype=dtype) - (size - 1) / 2.0
    profile = torch.exp(-(offsets**2) / (2.0 * sigma**2))
    profile = profile / profile.sum()
    return profile[:, None] * profile[None, :]


def ssim_map(
    pred: Float[Tensor, "*B H W 3"], gt: Float[Tensor, "*B H W 3"], padding: SsimPadding = SSIM_DEFAULT_PADDING
) -> Float[Tensor, "B 3 Ho Wo"]:
    """Per-pixel, per-channel SSIM map.

    With padding "valid" the 11x11 window is only placed where it fits inside the image, giving
    [B, 3, H - 10, W - 10]; "reflect" and "zero" pad the images by 5 pixels first (reflected or
    with zeros) and give [B, 3, H, W]. Images must be at least 11x11.
    """
    pred_b, gt_b = _check_pair(pred, gt)
    height, width = pred_b.shape[1:3]
    if height < SSIM_WINDOW_SIZE or width < SSIM_WINDOW_SIZE:
        raise ValueError(f"ssim: images of {height}x{width} are smaller than the {SSIM_WINDOW_SIZE}x{SSIM_WINDOW_SIZE} window")
    x = pred_b.permute(0, 3, 1, 2)
    y = gt_b.permute(0, 3, 1, 2)
    half = (SSIM_WINDOW_SIZE - 1) // 2
    if padding == "reflect":
        x, y = (F.pad(v, (half, half, half, half), mode="reflect") for v in (x, y))
    elif padding == "zero":
        x, y = (F.pad(v, (half, half, half, half), mode="constant", value=0.0) for v in (x, y))
    elif padding != "valid":
        raise ValueError(f"ssim: padding must be 'valid', 'reflect' or 'zero', got {padding!r}")
    window = gaussian_window(device=x.device, dtype=x.dtype).expand(NUM_CHANNELS, 1, -1, -1)

    def blur(image: Tensor) -> Tensor:
        return F.conv2d(image, window, groups=NUM_CHANNELS)

    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x**2
    var_y = blur(y * y) - mu_y**2
    cov_xy = blur(x * y) - mu_x * mu_y
    c1 = (SSIM_K1 * DATA_RANGE) ** 2
    c2 = (SSIM_K2 * DATA_RANGE) ** 2
    luminance = (2.0 * mu_x * mu_y + c1) / (mu_x**2 + mu_y**2 + c1)
    contrast_structure = (2.0 * cov_xy + c2) / (var_x + var_y + c2)
    return luminance * contrast_structure


def ssim(pred: Float[Tensor, "*B H W 3"], gt: Float[Tensor, "*B H W 3"], padding: SsimPadding = SSIM_DEFAULT_PADDING) -> float:
    """Structural similarity (Wang et al. 2004), mean over pixels, channels and images.

    11x11 Gaussian window, sigma 1.5 pixels, K1 = 0.01, K2 = 0.03, data range 1. The border is
    handled by `padding` (see `SsimPadding`): "valid" by default; "reflect" reproduces
    torchmetrics' StructuralSimilarityIndexMeasure, "zero" the 3DGS-family metric scripts.

    Args:
        pred: [H, W, 3] or [B, H, W, 3] prediction in [0, 1], H and W >= 11.
        gt: same shape as `pred`, ground truth in [0, 1].
        padding: "valid", "reflect" or "zero".

    Returns:
        SSIM in [-1, 1]; 1 for identical images.
    """
    return float(ssim_map(pred, gt, padding).mean().item())


def mask_iou(pred_mask: Float[Tensor, "H W"], gt_mask: Bool[Tensor, "H W"], threshold: float = 0.5) -> float:
    """Intersection over union of a soft predicted mask and a binary ground-truth mask.

    A predicted pixel is foreground when `pred_mask >= threshold`. If both masks are empty the
    union is empty and the masks agree perfectly: the result is `EMPTY_UNION_IOU` (1.0).

    Args:
        pred_mask: [H, W] float rendered motion mask, values in [0, 1].
        gt_mask: [H, W] bool ground-truth dynamic-region mask (non-bool is read as != 0).
        threshold: binarisation level for `pred_mask`.

    Returns:
        IoU in [0, 1].
    """
    if pred_mask.dim() != 2:
        raise ValueError(f"mask_iou: pred_mask has shape {tuple(pred_mask.shape)}, expected [H, W]")
    if gt_mask.shape != pred_mask.shape:
        raise ValueError(f"mask_iou: gt_mask has shape {tuple(gt_mask.shape)}, pred_mask has {tuple(pred_mask.shape)}")
    pred_bin = pred_mask >= threshold
    gt_bin = gt_mask.to(device=pred_mask.device) != 0
    union = int((pred_bin | gt_bin).sum().item())
    if union == 0:
        return EMPTY_UNION_IOU
    intersection = int((pred_bin & gt_bin).sum().item())
    return intersection / union

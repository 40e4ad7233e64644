"""The event-based double integral (EDI): sharp latent frames from one blurry frame and its events.

Discrete form with k latents (reference-notes.md): with b_1..b_{k-1} the signed event counts
between consecutive latent times, S_0 = 0 and S_j = sum_{i<=j} b_i per pixel, the blurry
frame B is the mean of the latents, L_j = L_0 exp(theta S_j), hence

    L_0 = k B / sum_{j=0}^{k-1} exp(theta S_j),    L_j = L_0 exp(theta S_j).

Everything is in linear intensity; every colour channel shares the same S (grey events).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from edygs_ns.events.color import decode_to_linear, encode_from_linear
from edygs_ns.io.images import UINT8_MAX



@dataclass
class EdiConfig:
    """How blurry frames are turned into latent frames."""

    k: int = 5
    """Latent (sharp) frames per blurry frame, evenly spaced over the exposure (k - 1 event bins)."""
    theta: float = 0.2
    """Event contrast threshold: one event is a change of theta in log intensity."""
    color_space: Literal["linear", "srgb"] = "linear"
    """Encoding of the input pixels. "linear" (default): pixel values are linear intensity, as
    DAVIS APS frames are linear sensor readings and E2NeRF's data and EDI apply exp(theta*S) to
    pixel values directly. "srgb": decode sRGB before EDI and re-encode the latents after."""
    clip_max: float = 1.0
    """Latent linear intensity is clipped to [0, clip_max] before re-encoding."""


def edi_latents(blurry: np.ndarray, bins: np.ndarray, theta: float) -> np.ndarray:
    """Latent frames of one exposure by the discrete EDI.

    Args:
        blurry: [H, W] or [H, W, C] float, linear intensity of the blurry frame.
        bins: [k-1, H, W] signed event counts between consecutive latent times.
        theta: contrast threshold (log-intensity change per event), > 0.

    Returns:
        [k, H, W] or [k, H, W, C] latent linear intensities (float32), latent 0 at the
        exposure start; their mean over k equals ``blurry``.

    Raises:
        ValueError: shapes disagree or theta <= 0.
    """
    blurry = np.asarray(blurry)
    bins = np.asarray(bins)
    if blurry.ndim not in (2, 3):
        raise ValueError(f"edi_latents: blurry must be [H, W] or [H, W, C], got shape {blurry.shape}")
    if bins.ndim != 3 or bins.shape[1:] != blurry.shape[:2]:
        raise ValueError(f"edi_latents: bins must be [k-1, H, W] matching blurry {blurry.shape}, got {bins.shape}")
    if not theta > 0:
        raise ValueError(f"edi_latents: theta must be positive, got {theta}")
    k = bins.shape[0] + 1
    s = np.zeros((k,) + bins.shape[1:], dtype=np.float64)
    np.cumsum(bins, axis=0, dtype=np.float64, out=s[1:])
    log_ratio = theta * s
    # Subtract the per-pixel maximum before exp: same ratios, no overflow for large counts.
    weights = np.exp(log_ratio - log_ratio.max(axis=0, keepdims=True))
    shares = k * weights / weights.sum(axis=0, keepdims=True)  # L_j / B, [k, H, W]
    if blurry.ndim == 3:
        shares = shares[..., None]
    return (shares * blurry[None].astype(np.float64)).astype(np.float32)


def edi_from_frame(image: np.ndarray, bins: np.ndarray, config: EdiConfig) -> np.ndarray:
    """Latent frames from a stored blurry image: decode, EDI, clip, re-encode.

    Args:
        image: [H, W] or [H, W, C] uint8 (0..255) or float (0..1) pixels in config.color_space.
        bins: [k-1, H, W] signed event counts, k = config.k.
        config: EDI settings.

    Returns:
        [k, H, W(, C)] float32 latents in the input's colour encoding, in [0, 1] for the default
        clip_max of 1.

    Raises:
        ValueError: the bin count is not config.k - 1, or shapes disagree.
    """
    if np.asarray(bins).shape[0] != config.k - 1:
        raise ValueError(f"edi_from_frame: expected {config.k - 1} bins for k={config.k}, got {np.asarray(bins).shape[0]}")
    image = np.asarray(image)
    pixels = image.astype(np.float32) / UINT8_MAX if image.dtype == np.uint8 else image.astype(np.float32)
    linear = decode_to_linear(pixels, config.color_space)
    latents = np.clip(edi_latents(linear, bins, config.theta), 0.0, config.clip_max)
    return np.asarray(encode_from_linear(latents, config.color_space), dtype=np.float32)

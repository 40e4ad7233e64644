"""The event loss between two consecutive latent renders.

Form (documented choice; the paper gives L(ln Ĉ_{i+1} − ln Ĉ_i, Θ Σ e)):

    Δ̂ = ln(g(Ĉ_b) + ε) − ln(g(Ĉ_a) + ε),   target = Θ · E_{a→b}
    L_event = mean over all pixels of |Δ̂ − target|

with g the luma 0.299 R + 0.587 G + 0.114 B of the *linear* rendered intensity (renders in an
sRGB-encoded dataset are decoded first) and ε = ``log_eps`` keeping the log finite where the
render is black (the same ε the simulator uses). Every pixel counts: a pixel with no event says
the log change stayed within one threshold, which is information too (E2NeRF used only pixels
with events; we found all-pixel L1 more stable for the static background).
"""

from __future__ import annotations

import functools

import torch
from jaxtyping import Float
from torch import Tensor

#: ITU-R BT.601 luma weights, as used by E2NeRF and v2e.
LUMA_WEIGHTS = (0.299, 0.587, 0.114)
#: default ε in ln(I + ε); equals the simulator's default.
DEFAULT_LOG_EPS = 1e-3


@functools.lru_cache(maxsize=None)
def _luma_weights(device: torch.device, dtype: torch.dtype) -> Tensor:
    """LUMA_WEIGHTS as a [3] tensor, made once per device and dtype (no upload per call)."""
    return torch.tensor(LUMA_WEIGHTS, dtype=dtype, device=device)


def luma(image: Float[Tensor, "*B H W 3"]) -> Float[Tensor, "*B H W"]:
    """Grey intensity of a linear RGB image."""
    return (image * _luma_weights(image.device, image.dtype)).sum(dim=-1)


def log_intensity(image: Float[Tensor, "*B H W 3"], log_eps: float = DEFAULT_LOG_EPS) -> Float[Tensor, "*B H W"]:
    """ln(luma + ε) of a linear RGB image (ε > 0 avoids ln 0)."""
    if log_eps <= 0:
        raise ValueError(f"log_eps must be > 0, got {log_eps}")
    return torch.log(luma(image) + log_eps)


def predicted_event_count(
    render_a: Float[Tensor, "H W 3"], render_b: Float[Tensor, "H W 3"], theta: float, log_eps: float = DEFAULT_LOG_EPS
) -> Float[Tensor, "H W"]:
    """(ln I_b − ln I_a) / Θ: the signed event count the renders imply."""
    return (log_intensity(render_b, log_eps) - log_intensity(render_a, log_eps)) / theta


def event_loss(
    render_a: Float[Tensor, "H W 3"],
    render_b: Float[Tensor, "H W 3"],
    event_map: Float[Tensor, "H W"],
    theta: float,
    log_eps: float = DEFAULT_LOG_EPS,
) -> Tensor:
    """Mean |(ln I_b − ln I_a) − Θ·E| over all pixels (renders in linear intensity)."""
    if render_a.shape != render_b.shape or render_a.shape[:-1] != event_map.shape:
        raise ValueError(
            f"event_loss: renders {tuple(render_a.shape)}, {tuple(render_b.shape)} and event map "
            f"{tuple(event_map.shape)} do not match"
        )
    delta = log_intensity(render_b, log_eps) - log_intensity(render_a, log_eps)
    return (delta - theta * event_map).abs().mean()

"""End to end on CPU: fit Gaussians (with a mask channel and densification) to rendered targets."""

from __future__ import annotations

import math
from typing import Dict

import pytest
import torch
from torch import Tensor

from edygs_ns.model.strategy import LAST_REFINE_KEY, DensifyConfig, make_strategy, strategy_info
from edygs_ns.render.torch_backend import rasterize_torch

SIZE = 24
FOCAL = 30.0
N_TARGET, N_INIT = 24, 8
ITERATIONS = 300
LEARNING_RATES = {"means": 0.02, "scales": 0.04, "quats": 0.04, "opacities": 0.1, "colors": 0.1, "mask_logit": 0.1}


pytestmark = pytest.mark.usefixtures("one_thread")


def cameras() -> Dict[str, Tensor]:
    """Two cameras 3 units in front of the origin, the second slightly to the side (OpenCV)."""
    viewmats = torch.eye(4).repeat(2, 1, 1)
    viewmats[:, 2, 3] = 3.0
    viewmats[1, 0, 3] = 0.3
    ks = torch.tensor([[FOCAL, 0.0, SIZE / 2], [0.0, FOCAL, SIZE / 2], [0.0, 0.0, 1.0]]).repeat(2, 1, 1)
    return {"viewmats": viewmats, "Ks": ks}


def render(params: Dict[str, Tensor], cams: Dict[str, Tensor]):
    """RGB + mask channels of raw parameters (log scales, logit opacities / colours / mask)."""
    features = torch.cat([torch.sigmoid(params["colors"]), torch.sigmoid(params["mask_logit"])], dim=-1)
    return rasterize_torch(
        params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]).squeeze(-1),
        features, cams["viewmats"], cams["Ks"], SIZE, SIZE, backgrounds=torch.tensor([[0.1, 0.1, 0.1, 0.0]] * 2),
    )


def random_params(n: int, seed: int, scale: float) -> Dict[str, Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "means": (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([1.6, 1.6, 0.6]),
        "scales": torch.full((n, 3), math.log(scale)) + 0.2 * torch.randn(n, 3, generator=g),
        "quats": torch.randn(n, 4, generator=g),
        "opacities": torch.randn(n, 1, generator=g),
        "colors": 2.0 * torch.randn(n, 3, generator=g),
        "mask_logit": 3.0 * torch.randn(n, 1, generator=g),
    }


def test_fit_with_densification_reduces_loss_tenfold() -> None:
    torch.manual_seed(0)
    cams = cameras()
    with torch.no_grad():
        target = render(random_params(N_TARGET, seed=1, scale=0.08), cams).render
    params = {k: torch.nn.Parameter(v) for k, v in random_params(N_INIT, seed=2, scale=0.15).items()}
    optimizers = {k: torch.optim.Adam([p], lr=LEARNING_RATES[k]) for k, p in params.items()}
    strategy = make_strategy(
        DensifyConfig(refine_start_iter=50, refine_every=50, refine_stop_iter=250, reset_every=10_000, grow_grad2d=2e-4)
    )
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=1.0)
    losses, n_refined = [], 0
    for step in range(ITERATIONS):
        out = render(params, cams)
        info = strategy_info(out, SIZE, SIZE)
        strategy.step_pre_backward(params, optimizers, state, step, info)
        loss = (out.render - target).abs().mean()
        loss.backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        strategy.step_post_backward(params, optimizers, state, step, info)
        if state.get(LAST_REFINE_KEY, {}).get("step") == step:
            n_refined += state[LAST_REFINE_KEY]["duplicated"] + state[LAST_REFINE_KEY]["split"]
        losses.append(float(loss.detach()))
    assert n_refined > 0, "densification never grew a Gaussian"
    assert params["mask_logit"].shape == (len(params["means"]), 1)
    start, end = sum(losses[:5]) / 5, sum(losses[-5:]) / 5
    assert end < start / 10, f"L1 went from {start:.4f} to {end:.4f}"

"""Densification on CPU: extra attributes and Adam state stay aligned with their Gaussians."""

from __future__ import annotations

import math
from typing import Dict

import pytest
import torch
from torch import Tensor

from edygs_ns.model.strategy import LAST_REFINE_KEY, DensifyConfig, make_strategy, strategy_info
from edygs_ns.render.torch_backend import rasterize_torch

IMAGE = 100  # width = height used for the gradient normalisation
REFINE_STEP = 600
SPLIT_SHRINK = 1.6  # gsplat's split divides scales by this


pytestmark = pytest.mark.usefixtures("one_thread")


def make_params() -> Dict[str, torch.nn.Parameter]:
    """Four Gaussians: 0 small, 1 large, 2 transparent, 3 plain; mask_logit identifies them."""
    raw = {
        "means": torch.tensor([[0.0, 0.0, 3.0], [0.5, 0.0, 3.0], [0.0, 0.5, 3.0], [0.5, 0.5, 3.0]]),
        "scales": torch.log(torch.tensor([[0.001] * 3, [0.5] * 3, [0.001] * 3, [0.001] * 3])),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 4),
        "opacities": torch.tensor([[0.0], [0.0], [-10.0], [0.0]]),  # logits: 0.5, 0.5, 4.5e-5, 0.5
        "features_dc": torch.arange(12, dtype=torch.float32).reshape(4, 3),
        "features_rest": torch.arange(36, dtype=torch.float32).reshape(4, 3, 3),
        "mask_logit": torch.tensor([[10.0], [11.0], [12.0], [13.0]]),
        "extra_1d": torch.tensor([20.0, 21.0, 22.0, 23.0]),  # an [N] attribute
    }
    return {k: torch.nn.Parameter(v) for k, v in raw.items()}


def make_optimizers(params: Dict[str, torch.nn.Parameter]) -> Dict[str, torch.optim.Optimizer]:
    """One Adam per attribute, stepped once with gradient (row index + 1) so moments are known."""
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    for p in params.values():
        rows = torch.arange(1, p.shape[0] + 1, dtype=p.dtype).reshape(-1, *([1] * (p.dim() - 1)))
        p.grad = rows.expand_as(p).clone()
    for opt in optimizers.values():
        opt.step()
    return optimizers


def fake_info(n: int, high: Tensor) -> Dict[str, object]:
    """An info dict as a rasteriser would give: means2d.grad large where ``high``."""
    means2d = torch.zeros(1, n, 2, requires_grad=True)
    means2d.grad = torch.zeros(1, n, 2)
    means2d.grad[0, high, 0] = 1e-3  # pixels; x (width / 2) = 0.05 NDC >> grow_grad2d
    return {"means2d": means2d, "radii": torch.full((1, n), 5, dtype=torch.int32), "width": IMAGE,
            "height": IMAGE, "n_cameras": 1, "gaussian_ids": None}


def config() -> DensifyConfig:
    return DensifyConfig(refine_start_iter=500, refine_every=100, reset_every=3000, refine_stop_iter=15_000)


def assert_optimizer_aligned(params: Dict[str, torch.nn.Parameter], optimizers: Dict[str, torch.optim.Optimizer]) -> None:
    for name, p in params.items():
        group = optimizers[name].param_groups[0]["params"]
        assert group[0] is p, f"{name}: the optimizer does not hold the new parameter"
        state = optimizers[name].state[p]
        assert state["exp_avg"].shape == p.shape and state["exp_avg_sq"].shape == p.shape, name


def test_clone_split_prune_keep_every_attribute_with_its_gaussian() -> None:
    torch.manual_seed(0)
    params = make_params()
    optimizers = make_optimizers(params)
    original = {k: v.detach().clone() for k, v in params.items()}
    moments = {k: optimizers[k].state[p]["exp_avg"].clone() for k, p in params.items()}
    strategy = make_strategy(config())
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=1.0)
    high = torch.tensor([True, True, False, False])
    strategy.step_post_backward(params, optimizers, state, REFINE_STEP, fake_info(4, high))

    # 0 is cloned (small), 1 split into two (large), 2 pruned (transparent), 3 untouched
    assert state[LAST_REFINE_KEY] == {"step": REFINE_STEP, "duplicated": 1, "split": 1, "pruned": 1}
    mask = params["mask_logit"].detach().squeeze(1)
    ident = [round(m) - 10 for m in mask.tolist()]  # Adam's first step moved the logits by its lr
    assert sorted(ident) == [0, 0, 1, 1, 3]
    assert_optimizer_aligned(params, optimizers)
    assert state["grad2d"].shape == (5,) and state["count"].shape == (5,)
    for row, src in enumerate(ident):
        for name in ("quats", "features_dc", "features_rest", "opacities", "mask_logit", "extra_1d"):
            assert torch.equal(params[name][row], original[name][src]), f"row {row} ({name}) lost its Gaussian"
        if src == 1:  # split: scales shrink, means are sampled around the parent
            assert torch.allclose(params["scales"][row], original["scales"][1] - math.log(SPLIT_SHRINK))
            assert (params["means"][row] - original["means"][1]).norm() < 5 * 0.5
        else:
            assert torch.equal(params["scales"][row], original["scales"][src])
            assert torch.equal(params["means"][row], original["means"][src])
    # Adam moments: kept Gaussians keep theirs, new ones start at zero
    for name, p in params.items():
        exp_avg = optimizers[name].state[p]["exp_avg"]
        assert torch.equal(exp_avg[0], moments[name][0]) and torch.equal(exp_avg[1], moments[name][3]), name
        assert torch.all(exp_avg[2:] == 0), name
    # the optimizers still step with the new shapes
    for p in params.values():
        p.grad = torch.ones_like(p)
    for opt in optimizers.values():
        opt.step()


def test_opacity_reset_touches_only_opacities() -> None:
    params = make_params()
    with torch.no_grad():
        params["opacities"].fill_(2.0)  # opacity 0.88: nothing is pruned
    optimizers = make_optimizers(params)
    before = {k: v.detach().clone() for k, v in params.items()}
    moments = {k: optimizers[k].state[p]["exp_avg"].clone() for k, p in params.items()}
    cfg = config()
    strategy = make_strategy(cfg)
    state = strategy.initialize_state(scene_scale=1.0)
    strategy.step_post_backward(params, optimizers, state, cfg.reset_every, fake_info(4, torch.zeros(4, dtype=torch.bool)))

    reset_value = torch.logit(torch.tensor(2.0 * cfg.prune_opa))
    assert torch.allclose(params["opacities"], reset_value.expand(4, 1))
    assert torch.all(optimizers["opacities"].state[params["opacities"]]["exp_avg"] == 0)
    for name in ("means", "scales", "quats", "features_dc", "features_rest", "mask_logit", "extra_1d"):
        assert torch.equal(params[name], before[name]), name
        assert torch.equal(optimizers[name].state[params[name]]["exp_avg"], moments[name]), name


def test_statistics_come_from_the_cpu_rasteriser() -> None:
    params = make_params()
    optimizers = make_optimizers(params)
    strategy = make_strategy(config())
    state = strategy.initialize_state(scene_scale=1.0)
    viewmats = torch.eye(4)[None]
    ks = torch.tensor([[[40.0, 0.0, 16.0], [0.0, 40.0, 16.0], [0.0, 0.0, 1.0]]])
    features = torch.cat([params["features_dc"] / 12.0, torch.sigmoid(params["mask_logit"])], dim=-1)
    out = rasterize_torch(
        params["means"], params["quats"], torch.exp(params["scales"]) + 0.05, torch.sigmoid(params["opacities"]).squeeze(1),
        features, viewmats, ks, 32, 32,
    )
    info = strategy_info(out, 32, 32)
    assert info["n_cameras"] == 1 and info["gaussian_ids"] is None
    strategy.step_pre_backward(params, optimizers, state, 1, info)
    (out.render * torch.rand_like(out.render)).sum().backward()
    strategy.step_post_backward(params, optimizers, state, 1, info)
    visible = out.visible[0]
    assert torch.equal(state["count"], visible.float())
    expected = (out.means2d.grad[0] * torch.tensor([16.0, 16.0])).norm(dim=-1) * visible
    torch.testing.assert_close(state["grad2d"], expected)
    assert torch.all(state["grad2d"][visible & (torch.sigmoid(params["opacities"]).squeeze(1) > 0.1)] > 0)


def test_absgrad_is_rejected() -> None:
    with pytest.raises(ValueError, match="absgrad"):
        make_strategy(DensifyConfig(absgrad=True))


def test_blur_loss_raises_the_grow_threshold() -> None:
    """A screen-space gradient between grow_grad2d and grow_grad2d_blur grows a Gaussian only
    while the blur-formation loss is off."""
    cfg = config()
    between = (cfg.grow_grad2d + cfg.grow_grad2d_blur) / 2 / (IMAGE / 2)  # pixels -> NDC in between
    grown = {}
    for blur in (False, True):
        params = make_params()
        optimizers = make_optimizers(params)
        strategy = make_strategy(cfg, blur_loss=blur)
        state = strategy.initialize_state(scene_scale=1.0)
        info = fake_info(4, torch.tensor([True, False, False, False]))
        info["means2d"].grad[0, 0, 0] = between
        strategy.step_post_backward(params, optimizers, state, REFINE_STEP, info)
        record = state[LAST_REFINE_KEY]
        grown[blur] = record["duplicated"] + record["split"]
    assert grown == {False: 1, True: 0}

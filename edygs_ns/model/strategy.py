"""Densification (3DGS clone / split / prune / opacity reset) on CPU and CUDA.

We reuse gsplat 1.4.0's ``DefaultStrategy``. Reading its code path: ``step_post_backward`` ->
``_update_state`` / ``_grow_gs`` / ``_prune_gs`` -> ``strategy.ops.duplicate / split / remove /
reset_opa`` is pure PyTorch (``split`` samples with ``gsplat.utils.normalized_quat_to_rotmat``,
plain torch; ``torch.cuda.empty_cache`` is a no-op without CUDA). The CUDA kernels of
``strategy/ops.py`` (``quat_scale_to_covar_preci``, ``compute_relocation``) are used only by the
MCMC strategy's relocation and noise injection, which we do not use, and gsplat's extension is
compiled lazily, so importing the strategy on a CPU-only machine is safe. Nothing needed
replacing; ``tests/test_strategy.py`` runs every step on CPU.

What the subclass adds: logging through nerfstudio's CONSOLE instead of print, and the counts of
the last refinement in ``state["last_refine"]`` for the model's metrics.

Parameter conventions (gsplat's): ``params`` is a dict of per-Gaussian tensors with first
dimension N, including "means", "scales" (log), "quats" (raw wxyz) and "opacities" (logit, [N] or
[N, 1]); every other entry (SH features, the motion-mask logit, ...) is cloned, split and pruned
with its Gaussian. ``optimizers`` maps each name to an optimizer with one param group.
Adam's moments are resized with the parameters (new Gaussians start at zero).

Gradient threshold units: ``info["means2d"].grad`` is dL/d(pixel) from both backends. gsplat
multiplies it by (width / 2, height / 2) and by the number of cameras in the batch (the loss is a
mean over them) before taking the norm, i.e. it accumulates the gradient with respect to
normalised device coordinates, per visible camera. That is the quantity the original 3DGS
rasteriser accumulates (its backward returns dL/d(NDC) = W/2 * dL/d(pixel)), so ``grow_grad2d``
compares directly with 3DGS's ``densify_grad_threshold`` (0.0002). A threshold quoted from code
that accumulates pixel-space gradients would have to be divided by W/2 first; the 7e-4 of the
reference notes, if it comes from a 3DGS-style rasteriser, is the same NDC quantity with a higher
bar (fewer new Gaussians). The default follows the authors (7e-4): on the built-in 128x96 scene
3DGS's 0.0002 grew 117k Gaussians (ten per pixel) in a 3000-iteration run, which made it 1.6x
slower for 0.2 dB.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Optional, Tuple

import torch
from gsplat.strategy import DefaultStrategy
from gsplat.strategy.ops import _update_param_with_optimizer
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor
from tyro.conf import Suppress

from edygs_ns.render.contract import RasterOutputs

#: key of the last refinement's counts in the strategy state (not a tensor: ops leave it alone).
LAST_REFINE_KEY = "last_refine"


@dataclass
class DensifyConfig:
    """3DGS densification schedule and thresholds (gsplat's DefaultStrategy). Fields marked
    ``Suppress`` are hidden from ``ns-train --help`` and the command line (docs/method.md,
    "Configuration notes")."""

    refine_start_iter: int = 500
    """first step at which Gaussians are cloned, split and pruned"""
    refine_stop_iter: int = 15_000
    """no refinement (and no gradient statistics) from this step on"""
    refine_every: int = 100
    """refine every this many steps"""
    reset_every: int = 3000
    """reset opacities to 2 * prune_opa every this many steps"""
    pause_refine_after_reset: Suppress[int] = 0
    """skip refinement for this many steps after an opacity reset"""
    grow_grad2d: float = 0.0007
    """mean screen-space gradient (as 3DGS) above which a Gaussian grows"""
    grow_grad2d_blur: float = 0.0014
    """grow_grad2d while the blur loss is on (its gradient joins in)"""
    grow_scale3d: float = 0.01
    """growing Gaussians under this fraction of the scene scale are cloned, others split"""
    prune_opa: float = 0.005
    """Gaussians with opacity below this are pruned"""
    prune_scale3d: float = 0.1
    """after an opacity reset, Gaussians over this fraction of the scene scale are pruned"""
    revised_opacity: Suppress[bool] = False
    """split with the revised opacity rule of arXiv:2404.06109"""
    absgrad: Suppress[bool] = False
    """AbsGS's absolute gradients: no rasteriser backend computes them, so it must stay False"""
    verbose: bool = False
    """log the counts of every refinement"""


@dataclass
class PortableStrategy(DefaultStrategy):
    """gsplat's DefaultStrategy, logging through CONSOLE and recording refinement counts."""

    log_refinements: bool = False

    def _grow_gs(self, params, optimizers, state: Dict[str, Any], step: int) -> Tuple[int, int]:
        n_dupli, n_split = super()._grow_gs(params, optimizers, state, step)
        state[LAST_REFINE_KEY] = {"step": step, "duplicated": n_dupli, "split": n_split, "pruned": 0}
        return n_dupli, n_split

    def _prune_gs(self, params, optimizers, state: Dict[str, Any], step: int) -> int:
        n_prune = super()._prune_gs(params, optimizers, state, step)
        record = state.setdefault(LAST_REFINE_KEY, {"step": step, "duplicated": 0, "split": 0})
        record["pruned"] = n_prune
        if self.log_refinements:
            CONSOLE.log(
                f"step {step}: {record['duplicated']} cloned, {record['split']} split, {n_prune} pruned, "
                f"{len(params['means'])} Gaussians"
            )
        return n_prune

    def _update_state(self, params, state: Dict[str, Any], info: Dict[str, Any], packed: bool = False) -> None:
        """gsplat's running gradient statistics, without a host round trip: its version gathers the
        visible Gaussians (``torch.where`` on radii > 0, a device -> host read every step); here
        the invisible ones add zero. Only the first ``info["counted_cameras"]`` cameras of the
        call count (all when absent). Same sums: a Gaussian gets one term per counted camera."""
        if packed or self.absgrad:
            super()._update_state(params, state, info, packed=packed)
            return
        counted = info.get("counted_cameras", info["n_cameras"])
        grads = info["means2d"].grad[:counted].clone()  # [C', N, 2] dL/d(pixel)
        grads[..., 0] *= info["width"] / 2.0 * counted
        grads[..., 1] *= info["height"] / 2.0 * counted
        n_gaussian = len(list(params.values())[0])
        for key in ("grad2d", "count") + (("radii",) if self.refine_scale2d_stop_iter > 0 else ()):
            if state[key] is None:
                state[key] = torch.zeros(n_gaussian, device=grads.device)
        visible = info["radii"][:counted] > 0.0  # [C', N]
        norms = torch.where(visible, grads.norm(dim=-1), torch.zeros((), device=grads.device))
        state["grad2d"] += norms.sum(0)
        state["count"] += visible.sum(0).to(state["count"].dtype)
        if self.refine_scale2d_stop_iter > 0:
            scaled = torch.where(visible, info["radii"][:counted] / float(max(info["width"], info["height"])), 0.0)
            state["radii"] = torch.maximum(state["radii"], scaled.amax(0))


def make_strategy(config: DensifyConfig, blur_loss: bool = False) -> PortableStrategy:
    """The densification strategy for ``config`` (device-agnostic); ``blur_loss``: the blur-formation
    loss is on, so Gaussians grow above ``config.grow_grad2d_blur`` instead of ``grow_grad2d``.

    Raises:
        ValueError: when ``config.absgrad`` is set (no backend provides absolute gradients).
    """
    if config.absgrad:
        raise ValueError("DensifyConfig.absgrad: the rasteriser backends do not compute absolute gradients")
    return PortableStrategy(
        prune_opa=config.prune_opa,
        grow_grad2d=config.grow_grad2d_blur if blur_loss else config.grow_grad2d,
        grow_scale3d=config.grow_scale3d,
        prune_scale3d=config.prune_scale3d,
        refine_start_iter=config.refine_start_iter,
        refine_stop_iter=config.refine_stop_iter,
        reset_every=config.reset_every,
        refine_every=config.refine_every,
        pause_refine_after_reset=config.pause_refine_after_reset,
        absgrad=False,
        revised_opacity=config.revised_opacity,
        verbose=False,
        log_refinements=config.verbose,
    )


def strategy_info(outputs: RasterOutputs, width: int, height: int, counted_cameras: Optional[int] = None) -> Dict[str, Any]:
    """The ``info`` dict gsplat's strategy reads, from one rasteriser call (packed=False).

    Keys: "means2d" [C, N, 2] (its .grad is read after backward), "radii" [C, N], "width",
    "height", "n_cameras", "gaussian_ids" (None: not packed), "counted_cameras": the statistics
    come from the first this many cameras of the call (all when None).
    """
    n_cameras = int(outputs.means2d.shape[0])
    return {
        "means2d": outputs.means2d,
        "radii": outputs.radii,
        "width": width,
        "height": height,
        "n_cameras": n_cameras,
        "counted_cameras": n_cameras if counted_cameras is None else counted_cameras,
        "gaussian_ids": None,
    }


@torch.no_grad()
def append_gaussians(params, optimizers: Dict[str, torch.optim.Optimizer], state: Dict[str, Any], new: Dict[str, Tensor]) -> int:
    """Append Gaussians (``new``: one tensor per parameter name, same trailing shapes) with zero
    optimizer moments and zero densification statistics; returns how many were added."""
    count = next(iter(new.values())).shape[0]
    if count == 0:
        return 0

    def param_fn(name: str, p: Tensor) -> Tensor:
        return torch.nn.Parameter(torch.cat([p.detach(), new[name].to(p)]), requires_grad=p.requires_grad)

    def optimizer_fn(key: str, v: Tensor) -> Tensor:
        return torch.cat([v, torch.zeros((count, *v.shape[1:]), dtype=v.dtype, device=v.device)])

    _update_param_with_optimizer(param_fn, optimizer_fn, params, optimizers, names=list(new.keys()))
    for key, value in state.items():
        if isinstance(value, Tensor) and value.dim() > 0 and value.shape[0] == params["means"].shape[0] - count:
            state[key] = torch.cat([value, torch.zeros((count, *value.shape[1:]), dtype=value.dtype, device=value.device)])
    return count

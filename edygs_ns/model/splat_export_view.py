"""What lets nerfstudio's Gaussian-splat tools take an EDyGS model, and the time they see it at.

nerfstudio 1.1.5 recognises a Gaussian model only by ``isinstance(model, SplatfactoModel)``:
``ns-export gaussian-splat`` asserts it and then reads ``means``, ``shs_0``, ``shs_rest``,
``colors``, ``opacities`` (logits), ``scales`` (log), ``quats`` and ``config.sh_degree``; the
viewer uses it to pick the splat export panel, the z-depth path and ``set_background``.

:class:`SplatExportView` is a ``SplatfactoModel`` subclass that keeps none of splatfacto's
behaviour. Every attribute ``SplatfactoModel`` defines is overridden here, in one of four ways:

* nerfstudio's base ``Model`` behaviour (``__init__``, ``load_state_dict``,
  ``get_training_callbacks``, ``get_metrics_dict``), or an error asking the concrete model to define
  it where ``Model`` has none fit for a Gaussian model (``get_param_groups``, ``get_outputs``,
  ``get_loss_dict``, ``get_outputs_for_camera``, ``get_image_metrics_and_images``);
* an error for ``populate_modules`` (splatfacto's builds an LPIPS net, which downloads weights and
  calls ``.cuda()``: it must never run) and for splatfacto's internals (:data:`SPLATFACTO_INTERNALS`,
  which read splatfacto-only config and state and which only splatfacto's own methods call);
* read-only properties giving the Gaussians as ``ns-export`` reads them (:data:`EXPORT_PROPERTIES`),
  detached, with the deformation baked at :attr:`SplatExportView.fallback_time`; the exported PLY
  also carries ``motion_mask``, taken from the last model built (edygs_ns.model.ns_export_mask);
* ``set_background``: a no-op, renders keep ``config.background_color`` (the motion-mask channel
  needs a zero background).

Only the pure helpers of :data:`INHERITED_HELPERS` are inherited as they are.

Time. nerfstudio's tools give no time in two places: ``ns-export gaussian-splat`` (no option)
and cameras built without times (``ns-render interpolate``, ``camera-path`` keyframes without
``render_time``; ``spiral`` sweeps t from 0 to 1 by itself). Both use one normalised time in
[0, 1]: the environment variable ``EDYGS_TIME`` if set, else the model config's ``fallback_time``
(default 0.0, the start of the clip, also ``edygs-export``'s default). With ``use_deformation``
off the Gaussians are the canonical ones at every time.
"""

from __future__ import annotations

import math
import os
from typing import Any, Dict, FrozenSet, List

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes
from nerfstudio.models.splatfacto import SplatfactoModel
from torch import Tensor
from torch.nn import Parameter

from edygs_ns.model.appearance import SH_C0, SH_OFFSET
from edygs_ns.model.ns_export_mask import set_export_source

#: Environment variable overriding the model config's ``fallback_time`` (normalised clip time).
TIME_ENV = "EDYGS_TIME"
#: Time used when neither the environment nor the config gives one.
DEFAULT_FALLBACK_TIME = 0.0
#: Smallest scale passed to log (guards a zero after the deformation's scale offset).
MIN_SCALE = 1e-12

#: Properties ns-export (and the viewer) read, all overridden below.
EXPORT_PROPERTIES: FrozenSet[str] = frozenset(
    {
        "means", "scales", "quats", "opacities", "features_dc", "features_rest", "shs_0", "shs_rest", "colors",
        "num_points",
    }
)
#: Splatfacto's own machinery: overridden to raise, nothing of ours calls them.
SPLATFACTO_INTERNALS: FrozenSet[str] = frozenset(
    {
        "step_cb", "step_post_backward", "get_gaussian_param_groups", "_get_downscale_factor",
        "_downscale_if_required", "_get_background_color", "_apply_bilateral_grid", "get_gt_img",
    }
)
#: Pure helpers kept from SplatfactoModel: they touch no splatfacto config or state.
INHERITED_HELPERS: FrozenSet[str] = frozenset(
    {"k_nearest_sklearn", "set_crop", "get_empty_outputs", "composite_with_background"}
)


def resolve_time(config_time: float = DEFAULT_FALLBACK_TIME) -> float:
    """The time used where the host gives none: $EDYGS_TIME if set, else `config_time`.

    Raises:
        ValueError: the value is not a number in [0, 1].
    """
    raw = os.environ.get(TIME_ENV, "").strip()
    source = f"${TIME_ENV}" if raw else "fallback_time"
    try:
        value = float(raw) if raw else float(config_time)
    except ValueError:
        raise ValueError(f"{source} must be a number in [0, 1] (normalised clip time), got {raw!r}") from None
    if not (math.isfinite(value) and 0.0 <= value <= 1.0):
        raise ValueError(f"{source} must be in [0, 1] (normalised clip time), got {value}")
    return value


@torch.no_grad()
def bake_gaussians(model: torch.nn.Module, time: float) -> Dict[str, Tensor]:
    """The model's Gaussians with the deformation baked at `time`, in 3DGS storage form.

    Args:
        model: an EDyGS model (``gauss_params`` and ``deformed_gaussians(time, deform)``).
        time: normalised time in [0, 1].

    Returns:
        Detached float32 tensors on the model's device: ``means`` [N, 3], ``quats`` [N, 4] (unit,
        wxyz), ``log_scales`` [N, 3], ``opacity_logits`` [N, 1], ``features_dc`` [N, 3],
        ``features_rest`` [N, B-1, 3], ``mask`` [N] (motion mask m in [0, 1]).
    """
    if not 0.0 <= float(time) <= 1.0:
        raise ValueError(f"time must be in [0, 1] (normalised over the clip), got {time}")
    if not hasattr(model, "deformed_gaussians") or not hasattr(model, "gauss_params"):
        raise ValueError(f"{type(model).__name__} is not an EDyGS model (no deformed_gaussians)")
    deform = bool(getattr(getattr(model, "config", None), "use_deformation", True))
    g: Dict[str, Tensor] = model.deformed_gaussians(float(time), deform=deform)  # type: ignore[operator]
    params = model.gauss_params
    n = g["means"].shape[0]
    features_dc = params["features_dc"].detach().float().reshape(n, -1)
    if "d_colour" in g:  # rgb = SH_C0 · dc + ... + 0.5: an RGB offset is offset / SH_C0 on dc
        features_dc = features_dc + g["d_colour"].detach().float() / SH_C0
    return {
        "means": g["means"].detach().float(),
        "quats": torch.nn.functional.normalize(g["quats"].detach().float(), dim=-1),
        "log_scales": torch.log(g["scales"].detach().float().clamp_min(MIN_SCALE)),
        # the deformation leaves opacity alone; its colour offset, where it has one, goes into the DC term
        "opacity_logits": params["opacities"].detach().float().reshape(n, 1),
        "features_dc": features_dc,
        "features_rest": params["features_rest"].detach().float(),
        "mask": g["mask"].detach().float().reshape(n),
    }


class SplatExportView(SplatfactoModel):
    """Base of EdygsModel: passes ``isinstance(model, SplatfactoModel)`` without splatfacto's code
    (see the module docstring for what each inherited attribute became)."""

    # ------------------------------------------------ base-Model behaviour
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        # SplatfactoModel.__init__ would reset seed_points to None when the caller set it already
        if "seed_points" in kwargs:
            self.seed_points = kwargs.pop("seed_points")
        super(SplatfactoModel, self).__init__(*args, **kwargs)
        set_export_source(self)  # the model ns-export's motion_mask column comes from

    def populate_modules(self) -> None:
        raise NotImplementedError(
            f"{type(self).__name__} must define populate_modules: SplatfactoModel's must not run "
            "(it downloads LPIPS weights and calls .cuda())"
        )

    def load_state_dict(self, state_dict, *args: Any, **kwargs: Any):  # type: ignore[override]
        # not splatfacto's: it replaces the Parameter objects the optimizers hold and sets step = 30000
        return super(SplatfactoModel, self).load_state_dict(state_dict, *args, **kwargs)

    def get_training_callbacks(self, attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        return super(SplatfactoModel, self).get_training_callbacks(attributes)

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        raise NotImplementedError(f"{type(self).__name__} must define get_param_groups")

    def get_outputs(self, ray_bundle):  # type: ignore[override]
        raise NotImplementedError(f"{type(self).__name__} must define get_outputs")

    def get_metrics_dict(self, outputs, batch) -> Dict[str, Tensor]:
        return super(SplatfactoModel, self).get_metrics_dict(outputs, batch)

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, Tensor]:
        raise NotImplementedError(f"{type(self).__name__} must define get_loss_dict")

    def get_outputs_for_camera(self, camera, obb_box=None) -> Dict[str, Tensor]:  # type: ignore[override]
        raise NotImplementedError(f"{type(self).__name__} must define get_outputs_for_camera")

    def get_image_metrics_and_images(self, outputs, batch):  # type: ignore[override]
        raise NotImplementedError(f"{type(self).__name__} must define get_image_metrics_and_images")

    def set_background(self, background_color: Tensor) -> None:
        """Ignored (the viewer calls it every frame): renders use ``config.background_color``."""

    # ------------------------------------------------ splatfacto internals
    def _splatfacto_only(self, name: str) -> None:
        raise NotImplementedError(
            f"SplatfactoModel.{name} is splatfacto's machinery; {type(self).__name__} has its own"
        )

    def step_cb(self, *args: Any, **kwargs: Any) -> None:
        self._splatfacto_only("step_cb")

    def step_post_backward(self, *args: Any, **kwargs: Any) -> None:
        self._splatfacto_only("step_post_backward")

    def get_gaussian_param_groups(self) -> Dict[str, List[Parameter]]:  # type: ignore[return]
        self._splatfacto_only("get_gaussian_param_groups")

    def _get_downscale_factor(self) -> int:  # type: ignore[return]
        self._splatfacto_only("_get_downscale_factor")

    def _downscale_if_required(self, image: Tensor) -> Tensor:  # type: ignore[return]
        self._splatfacto_only("_downscale_if_required")

    def _get_background_color(self) -> Tensor:  # type: ignore[return]
        self._splatfacto_only("_get_background_color")

    def _apply_bilateral_grid(self, *args: Any, **kwargs: Any) -> Tensor:  # type: ignore[return]
        self._splatfacto_only("_apply_bilateral_grid")

    def get_gt_img(self, image: Tensor) -> Tensor:  # type: ignore[return]
        self._splatfacto_only("get_gt_img")

    # ------------------------------------------------ the Gaussians, as ns-export reads them
    @property
    def fallback_time(self) -> float:
        """Normalised time used where the host gives none ($EDYGS_TIME, else config.fallback_time)."""
        return resolve_time(getattr(self.config, "fallback_time", DEFAULT_FALLBACK_TIME))

    def _baked(self) -> Dict[str, Tensor]:
        """bake_gaussians at the fallback time, computed once while the time and every parameter
        stay the same (ns-export reads means, scales and quats, and the PLY writer the mask)."""
        key = (self.fallback_time, tuple((p.data_ptr(), p._version, tuple(p.shape)) for p in self.parameters()))
        cached = getattr(self, "_bake_cache", None)
        if cached is None or cached[0] != key:
            cached = (key, bake_gaussians(self, self.fallback_time))
            self._bake_cache = cached
        return cached[1]

    @property
    def num_points(self) -> int:
        return int(self.gauss_params["means"].shape[0])  # type: ignore[index]

    @property
    def means(self) -> Tensor:
        """[N, 3] centres at the fallback time."""
        return self._baked()["means"]

    @property
    def scales(self) -> Tensor:
        """[N, 3] log scales at the fallback time."""
        return self._baked()["log_scales"]

    @property
    def quats(self) -> Tensor:
        """[N, 4] unit quaternions (wxyz) at the fallback time."""
        return self._baked()["quats"]

    @property
    def opacities(self) -> Tensor:
        """[N, 1] opacity logits (time-independent)."""
        return self.gauss_params["opacities"].detach()  # type: ignore[index]

    @property
    def features_dc(self) -> Tensor:
        """[N, 3] SH degree-0 coefficients."""
        return self.gauss_params["features_dc"].detach()  # type: ignore[index]

    @property
    def features_rest(self) -> Tensor:
        """[N, B-1, 3] higher SH coefficients."""
        return self.gauss_params["features_rest"].detach()  # type: ignore[index]

    @property
    def shs_0(self) -> Tensor:
        # EDyGS always stores SH coefficients (splatfacto stores sigmoid logits at sh_degree 0)
        return self.features_dc

    @property
    def shs_rest(self) -> Tensor:
        return self.features_rest

    @property
    def colors(self) -> Tensor:
        """[N, 3] view-independent colour (degree-0 SH), not clamped."""
        return self.features_dc * SH_C0 + SH_OFFSET

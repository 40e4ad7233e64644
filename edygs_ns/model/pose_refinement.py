"""Per-latent pose refinement with a slower rotation: nerfstudio's camera optimiser, its rotation
corrections scaled by ``rotation_step`` (0.1 by default, the authors' ratio; 1 is nerfstudio's).

nerfstudio keeps one [N, 6] parameter (translation, then rotation as an axis-angle) in one Adam
group, so both parts take steps of about the same size (Adam normalises the gradient). The
authors step rotations at a tenth of the translations' learning rate (1e-5 against 1e-4,
reference notes). A rotation and a sideways move shift the image alike over one exposure's short
baseline, and with equal steps the refinement drifts slowly in rotation; the authors' 0.1 holds
part of that drift (docs/method.md, D24).
Here the rotation part of the parameter is multiplied by ``rotation_step`` before the exponential
map, which under Adam is a rotation learning rate ``rotation_step`` times the group's.
nerfstudio's regulariser (``rot_l2_penalty``) still applies to the parameter, i.e. to the applied
angle divided by ``rotation_step``.

The factor in use is kept in the checkpoint (buffer ``rotation_scale``), so a run renders with the
poses it trained; a checkpoint without it predates the factor and loads with 1.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, Literal, Type

import torch
from jaxtyping import Float, Int
from nerfstudio.cameras.camera_optimizers import CameraOptimizer, CameraOptimizerConfig
from nerfstudio.cameras.lie_groups import exp_map_SE3, exp_map_SO3xR3
from torch import Tensor

#: Buffer holding the rotation factor a run trained with (absent from older checkpoints: 1).
ROTATION_SCALE_KEY = "rotation_scale"
#: Translation components first, then rotation, in nerfstudio's [N, 6] pose adjustment.
TRANSLATION_DIMS = 3


@dataclass
class PoseRefinementConfig(CameraOptimizerConfig):
    """nerfstudio's camera-optimiser settings, plus the rotation's share of the step."""

    _target: Type = field(default_factory=lambda: PoseRefiner)
    mode: Literal["off", "SO3xR3", "SE3"] = "SO3xR3"
    """how each latent's pose is corrected (or off)"""
    rotation_step: float = 0.1
    """rotations step at this fraction of the translations' learning rate (authors: 0.1, D24; nerfstudio: 1)"""


class PoseRefiner(CameraOptimizer):
    """nerfstudio's ``CameraOptimizer`` whose rotation parameters are scaled by ``rotation_step``."""

    config: PoseRefinementConfig

    def __init__(self, config: PoseRefinementConfig, num_cameras: int, device: Any, **kwargs: Any) -> None:
        super().__init__(config, num_cameras, device, **kwargs)
        if self.non_trainable_camera_indices is not None:
            raise ValueError("PoseRefiner: every training camera is refined (no non_trainable_camera_indices)")
        step = float(config.rotation_step)
        if not step > 0:
            raise ValueError(f"camera_optimizer.rotation_step must be positive, got {step}")
        self.register_buffer(ROTATION_SCALE_KEY, torch.tensor(step, dtype=torch.float32, device=device))

    def _applied(self, raw: Float[Tensor, "C 6"]) -> Float[Tensor, "C 6"]:
        """Rows of the parameter as applied: translation as is, rotation times ``rotation_scale``."""
        scale = self.rotation_scale.to(raw.device, raw.dtype)
        return torch.cat([raw[:, :TRANSLATION_DIMS], raw[:, TRANSLATION_DIMS:] * scale], dim=-1)

    def adjustment(self) -> Float[Tensor, "N 6"]:
        """[N, 6] pose corrections as applied: translation (world units), rotation (axis-angle, rad)."""
        return self._applied(self.pose_adjustment)

    def forward(self, indices: Int[Tensor, "C"]) -> Float[Tensor, "C 3 4"]:
        """Correction matrices [C, 3, 4] of the cameras ``indices`` (identity when off)."""
        if self.config.mode == "off":
            return torch.eye(4, device=self.device)[None, :3, :4].tile(indices.shape[0], 1, 1)
        tangent = self._applied(self.pose_adjustment[indices.to(self.pose_adjustment.device), :])
        exp_map = exp_map_SO3xR3 if self.config.mode == "SO3xR3" else exp_map_SE3
        return exp_map(tangent)

    def prepare_load(self, state_dict: Dict[str, Tensor], prefix: str) -> None:
        """Give a checkpoint that predates the rotation factor (no ``rotation_scale``) the factor it
        trained with, in place: 1 where it refined poses, so an older run loads with its poses."""
        key = prefix + ROTATION_SCALE_KEY
        if key not in state_dict:
            legacy = prefix + "pose_adjustment" in state_dict
            state_dict[key] = torch.ones(()) if legacy else self.rotation_scale.detach().clone()

"""The three-phase EDyGS schedule as pure functions of the step.

1. ``POSE_INIT``: fit the Gaussians to the EDI latents at the initial poses; mask, poses and
   deformation frozen.
2. ``STATIC``: static region + motion-mask field + camera poses (event, EDI with the static
   term, mask L1, and our blur-formation loss).
3. ``DYNAMIC``: deformation on; mask and poses refined (motion loss, mask consistency; event,
   EDI and blur losses go on).

What trains and which losses count in each phase is decided here and nowhere else; the training
callback that applies it step by step is ``training/phase_driver.py``.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Dict, FrozenSet, Optional, Tuple, Union

from edygs_ns.losses.names import LossName, loss_name
from edygs_ns.model.gaussians import GAUSSIAN_ATTRIBUTES, MASK_ATTRIBUTE


class Phase(str, Enum):
    POSE_INIT = "pose_init"
    STATIC = "static"
    DYNAMIC = "dynamic"


#: parameter-group names (also the optimizer keys of the method config): one per Gaussian
#: attribute (the mask logit on its own), then the deformation MLP, the rigid motions and the poses.
MASK_GROUP = MASK_ATTRIBUTE
GAUSSIAN_GROUPS: FrozenSet[str] = frozenset(GAUSSIAN_ATTRIBUTES) - {MASK_GROUP}
CAMERA_GROUP = "camera_opt"
DEFORMATION_GROUP = "deformation"
RIGID_GROUP = "rigid_motion"

TRAINABLE: Dict[Phase, FrozenSet[str]] = {
    Phase.POSE_INIT: GAUSSIAN_GROUPS,
    Phase.STATIC: GAUSSIAN_GROUPS | {MASK_GROUP, CAMERA_GROUP},
    Phase.DYNAMIC: GAUSSIAN_GROUPS | {MASK_GROUP, CAMERA_GROUP, DEFORMATION_GROUP, RIGID_GROUP},
}

#: loss terms that are active in each phase (their weights live in the model config).
ACTIVE_LOSSES: Dict[Phase, FrozenSet[LossName]] = {
    Phase.POSE_INIT: frozenset({LossName.EDI}),
    Phase.STATIC: frozenset({LossName.EDI, LossName.EDI_STATIC, LossName.EVENT, LossName.BLUR, LossName.MASK_L1}),
    Phase.DYNAMIC: frozenset({LossName.EDI, LossName.EVENT, LossName.BLUR, LossName.MASK_CONSISTENCY, LossName.MOTION}),
}


@dataclass
class PhaseSchedule:
    """Phase lengths in iterations; the dynamic phase runs until the end of training."""

    pose_init_iters: int = 300
    """iterations of the pose-init warm-up (phase 1)"""
    static_iters: int = 1200
    """iterations of static-region reconstruction (phase 2) after the warm-up"""
    dynamic_window_start: float = 0.15
    """dynamic phase: latents first drawn within this half-width of the reference time"""
    dynamic_window_ramp_iters: int = 3000
    """the window widens to the whole clip over this many dynamic-phase iterations"""
    evidence_refresh_iters: int = 4000
    """dynamic-phase iterations before missed objects are looked for again (0: never)"""

    @property
    def static_start(self) -> int:
        return self.pose_init_iters

    @property
    def dynamic_start(self) -> int:
        return self.pose_init_iters + self.static_iters

    @property
    def refresh_step(self) -> Optional[int]:
        """The step at which the motion evidence is re-estimated, or None (never)."""
        return self.dynamic_start + self.evidence_refresh_iters if self.evidence_refresh_iters > 0 else None


def phase_at(step: int, schedule: PhaseSchedule) -> Phase:
    """The phase that training step ``step`` (0-based) belongs to."""
    if step < schedule.static_start:
        return Phase.POSE_INIT
    if step < schedule.dynamic_start:
        return Phase.STATIC
    return Phase.DYNAMIC


def is_trainable(group: str, phase: Phase) -> bool:
    """Whether parameter group ``group`` receives gradients in ``phase``."""
    return group in TRAINABLE[phase]


def is_active(loss: Union[str, LossName], phase: Phase) -> bool:
    """Whether loss term ``loss`` counts in ``phase``.

    Raises:
        ValueError: ``loss`` names no loss term (:class:`~edygs_ns.losses.names.LossName`).
    """
    return loss_name(loss) in ACTIVE_LOSSES[phase]


def time_window(step: int, schedule: PhaseSchedule, centre: float) -> Optional[Tuple[float, float]]:
    """The (lo, hi) normalised-time range training latents are drawn from at ``step``, or None for
    the whole clip (outside the dynamic phase's ramp). The half-width grows linearly from
    ``dynamic_window_start`` at the dynamic start to cover [0, 1] after ``dynamic_window_ramp_iters``."""
    if phase_at(step, schedule) is not Phase.DYNAMIC:
        return None
    reach = max(centre, 1.0 - centre)
    start = min(schedule.dynamic_window_start, reach)
    if start >= reach or schedule.dynamic_window_ramp_iters <= 0:
        return None
    progress = (step - schedule.dynamic_start) / schedule.dynamic_window_ramp_iters
    if progress >= 1.0:
        return None
    half = start + (reach - start) * progress
    return centre - half, centre + half

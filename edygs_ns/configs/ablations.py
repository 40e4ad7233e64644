"""Presets that reproduce the rows of the paper's Table 2 (and the blurry baseline) with one flag.

Each preset sets the model's ablation switches; ``full`` is EDyGS itself.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Dict

if TYPE_CHECKING:  # pragma: no cover
    from edygs_ns.model.edygs_model import EdygsModelConfig

#: switch values per preset (fields of EdygsModelConfig).
ABLATIONS: Dict[str, Dict[str, bool]] = {
    "events-only": dict(use_edi_loss=False, use_event_loss=True, optimize_poses=False, use_motion_mask=False),
    "edi-only": dict(use_edi_loss=True, use_event_loss=False, optimize_poses=False, use_motion_mask=False),
    "edi-events": dict(use_edi_loss=True, use_event_loss=True, optimize_poses=False, use_motion_mask=False),
    "edi-events-pose": dict(use_edi_loss=True, use_event_loss=True, optimize_poses=True, use_motion_mask=False),
    "full": dict(use_edi_loss=True, use_event_loss=True, optimize_poses=True, use_motion_mask=True),
    # blurry frames stand in for the EDI latents (the datamanager serves them): Deformable 3DGS
    "blurry": dict(use_edi_loss=True, use_event_loss=False, optimize_poses=False, use_motion_mask=False),
}


def apply_ablation(config: "EdygsModelConfig") -> None:
    """Set the switches of ``config`` from ``config.ablation`` (no-op when it is None).

    Presets without the motion mask have no static-phase work beyond the warm-up, and a preset
    without EDI supervision skips the warm-up (which fits the EDI latents only).
    """
    if config.ablation is None:
        return
    if config.ablation not in ABLATIONS:
        raise ValueError(f"unknown ablation {config.ablation!r}; choose one of {sorted(ABLATIONS)}")
    for name, value in ABLATIONS[config.ablation].items():
        setattr(config, name, value)
    if not config.use_edi_loss and config.schedule.pose_init_iters > 0:
        schedule = config.schedule
        config.schedule = replace(schedule, pose_init_iters=0, static_iters=schedule.static_iters + schedule.pose_init_iters)

"""Presets that reproduce the rows of the paper's Table 2 (and the blurry baseline) with one flag.

Each preset sets the model's ablation switches; ``full`` is EDyGS itself, with our blur-formation
loss (losses/blur.py), and ``paper`` is EDyGS with exactly the paper's losses (no blur loss). The
paper's rows below ``full`` have no blur loss either.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Dict

if TYPE_CHECKING:  # pragma: no cover
    from edygs_ns.model.edygs_model import EdygsModelConfig

#: switch values per preset (fields of EdygsModelConfig).
ABLATIONS: Dict[str, Dict[str, bool]] = {
    "events-only": dict(use_edi_loss=False, use_event_loss=True, optimize_poses=False, use_motion_mask=False, use_blur_loss=False),
    "edi-only": dict(use_edi_loss=True, use_event_loss=False, optimize_poses=False, use_motion_mask=False, use_blur_loss=False),
    "edi-events": dict(use_edi_loss=True, use_event_loss=True, optimize_poses=False, use_motion_mask=False, use_blur_loss=False),
    "edi-events-pose": dict(use_edi_loss=True, use_event_loss=True, optimize_poses=True, use_motion_mask=False, use_blur_loss=False),
    "paper": dict(use_edi_loss=True, use_event_loss=True, optimize_poses=True, use_motion_mask=True, use_blur_loss=False),
    "full": dict(use_edi_loss=True, use_event_loss=True, optimize_poses=True, use_motion_mask=True, use_blur_loss=True),
    # blurry frames stand in for the EDI latents (the datamanager serves them): Deformable 3DGS
    "blurry": dict(use_edi_loss=True, use_event_loss=False, optimize_poses=False, use_motion_mask=False, use_blur_loss=False),
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

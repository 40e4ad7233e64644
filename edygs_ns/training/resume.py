"""Resuming training (``ns-train ... --load-dir``) with the phase schedule it was saved under, or refusing.

The static -> dynamic switch happens once: it renders the motion masks M̂ and seeds the dynamic
Gaussians (the model keeps M̂ in its ``static_masks`` buffer, so a checkpoint records whether it
happened). Phases are monotone in the step, so only a changed schedule can resume a checkpoint
that already switched at a step the schedule puts before the switch: training would go back to
the static phase with dynamic seeds in the scene and never switch again. That is refused. The
other change, a later checkpoint that had not switched resuming inside the dynamic phase, is
correct: the switch happens at the first resumed step.
"""

from __future__ import annotations

from edygs_ns.model.phases import Phase, PhaseSchedule, phase_at


def check_resume_phase(step: int, schedule: PhaseSchedule, switched: bool) -> None:
    """Raise ValueError when a checkpoint that entered the dynamic phase resumes before the schedule's switch.

    Args:
        step: the training step about to run.
        schedule: the phase schedule of this run.
        switched: whether the model has been through the static -> dynamic switch (M̂ stored).

    Raises:
        ValueError: switched, but ``schedule`` puts ``step`` in an earlier phase (names both).
    """
    phase = phase_at(step, schedule)
    if switched and phase is not Phase.DYNAMIC:
        raise ValueError(
            f"resuming at step {step}: the checkpoint already entered the dynamic phase (motion masks and dynamic "
            f"seeds are in it), but this run's schedule puts step {step} in the {phase.value} phase (dynamic from step "
            f"{schedule.dynamic_start}). Resume with the schedule it was trained with (pose_init_iters, static_iters), "
            "or train from the start"
        )

"""Resuming with a changed phase schedule: correct, or refused with a clear message."""

from __future__ import annotations

import pytest

from edygs_ns.training.resume import check_resume_phase
from edygs_ns.model.phases import PhaseSchedule


def test_resume_after_the_switch_into_an_earlier_phase_is_refused() -> None:
    longer = PhaseSchedule(pose_init_iters=10, static_iters=100)  # dynamic from step 110
    with pytest.raises(ValueError, match=r"step 60: the checkpoint already entered the dynamic phase .* static phase "
                                         r"\(dynamic from step 110\)\. Resume with the schedule"):
        check_resume_phase(60, longer, switched=True)


def test_resumes_that_stay_consistent_are_accepted() -> None:
    schedule = PhaseSchedule(pose_init_iters=10, static_iters=40)  # dynamic from step 50
    check_resume_phase(60, schedule, switched=True)   # switched, still dynamic
    check_resume_phase(60, schedule, switched=False)  # not yet switched: the switch happens now
    check_resume_phase(20, schedule, switched=False)  # static, nothing switched

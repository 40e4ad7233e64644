"""The run-length scaling of the EDyGS schedule (the CPU demo and the benchmarks)."""

from __future__ import annotations

import pytest

from edygs_ns.configs.method_configs import MAX_ITERATIONS
from edygs_ns.configs.run_length import RunShape, run_length_args
from edygs_ns.training.schedule import PhaseSchedule


def _as_dict(args):
    return {key: int(value) for key, value in zip(args[::2], args[1::2])}


def test_a_short_run_keeps_the_shape_of_the_schedule():
    args = _as_dict(run_length_args(3000))
    assert args == {
        "--max-num-iterations": 3000,
        "--pipeline.model.schedule.pose-init-iters": 300,
        "--pipeline.model.schedule.static-iters": 900,
        "--pipeline.model.schedule.dynamic-window-ramp-iters": 450,
        "--pipeline.model.densify.refine-start-iter": 200,
        "--pipeline.model.densify.refine-stop-iter": 2250,
    }
    # the time window widens over the same share of the run as at full length
    assert PhaseSchedule().dynamic_window_ramp_iters / MAX_ITERATIONS == pytest.approx(RunShape().window_ramp)
    with pytest.raises(ValueError, match="iters must be >= 10"):
        run_length_args(5)

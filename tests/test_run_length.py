"""The run-length scaling of the EDyGS schedule (the CPU demo and the benchmarks)."""

from __future__ import annotations

import pytest

from edygs_ns.configs.method_configs import MAX_ITERATIONS
from edygs_ns.configs.run_length import RunShape, run_length_args
from edygs_ns.model.phases import PhaseSchedule


def _as_dict(args):
    return {key: int(value) for key, value in zip(args[::2], args[1::2])}


def test_a_short_run_keeps_the_shape_of_the_schedule():
    args = _as_dict(run_length_args(3000))
    assert args == {
        "--max-num-iterations": 3000,
        "--pipeline.model.schedule.pose-init-iters": 300,
        "--pipeline.model.schedule.static-iters": 900,
        "--pipeline.model.schedule.dynamic-window-ramp-iters": 450,
        "--pipeline.model.schedule.evidence-refresh-iters": 600,
        "--pipeline.model.densify.refine-start-iter": 200,
        "--pipeline.model.densify.refine-stop-iter": 2250,
    }
    # the time window widens over the same share of the run as at full length
    assert PhaseSchedule().dynamic_window_ramp_iters / MAX_ITERATIONS == pytest.approx(RunShape().window_ramp)
    assert PhaseSchedule().evidence_refresh_iters / MAX_ITERATIONS == pytest.approx(RunShape().refresh)
    with pytest.raises(ValueError, match="iters must be >= 10"):
        run_length_args(5)


def test_the_cpu_methods_are_the_demo_run():
    from edygs_ns.configs.method_configs import blurry_baseline_cpu_method, edygs_cpu_method
    from edygs_ns.configs.run_length import CPU_DEFORMATION, CPU_ITERATIONS

    args = _as_dict(run_length_args(CPU_ITERATIONS))
    for spec, name in ((edygs_cpu_method, "edygs-cpu"), (blurry_baseline_cpu_method, "edygs-blurry-cpu")):
        config = spec.config
        model = config.pipeline.model
        got = {
            "--max-num-iterations": config.max_num_iterations,
            "--pipeline.model.schedule.pose-init-iters": model.schedule.pose_init_iters,
            "--pipeline.model.schedule.static-iters": model.schedule.static_iters,
            "--pipeline.model.schedule.dynamic-window-ramp-iters": model.schedule.dynamic_window_ramp_iters,
            "--pipeline.model.schedule.evidence-refresh-iters": model.schedule.evidence_refresh_iters,
            "--pipeline.model.densify.refine-start-iter": model.densify.refine_start_iter,
            "--pipeline.model.densify.refine-stop-iter": model.densify.refine_stop_iter,
        }
        assert got == args and config.method_name == name and config.machine.device_type == "cpu"
        assert (model.deformation.depth, model.deformation.width, model.deformation.skip_layer) == CPU_DEFORMATION
    # the GPU method keeps the paper's full length and MLP
    from edygs_ns.configs.method_configs import edygs_method

    assert edygs_method.config.max_num_iterations == MAX_ITERATIONS and edygs_method.config.pipeline.model.deformation.width == 256

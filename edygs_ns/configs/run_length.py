"""One place that scales the EDyGS schedule to a run length (the CPU demo and benchmarks).

The method's defaults (``configs/method_configs.py``) are for a full-length GPU run. A shorter
run has one shape, ``RunShape``: phase lengths, the dynamic-phase time curriculum and the
densification window are fractions of the run (the phase fractions are not the full-length
defaults' 5 % / 20 %). The learning-rate decays are not scaled: they keep the full-length
schedules (20k steps), so a short run ends at a higher rate (scaling them was worse). Both are
in docs/method.md, "Run shape". ``python -m edygs_ns.configs.run_length ITERS`` prints the
``ns-train`` arguments (the demo script uses them); ``ns-train edygs-cpu`` is the same run.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import List


@dataclass(frozen=True)
class RunShape:
    """Fractions of the run given to each part of the schedule."""

    pose_init: float = 0.1
    """pose-init warm-up"""
    static: float = 0.3
    """static phase"""
    window_ramp: float = 0.15
    """widening of the dynamic-phase time window, from the dynamic start (the
    full-length share, 3000 of 20k; docs/method.md)"""
    refresh: float = 0.2
    """motion-evidence refresh, counted from the dynamic start (after the window
    has widened to the whole clip)"""
    refine_start: float = 1.0 / 15.0
    """first densification step"""
    refine_stop: float = 0.75
    """last densification step"""


def run_length_args(iters: int, shape: RunShape = RunShape()) -> List[str]:
    """``ns-train edygs`` arguments for an ``iters``-iteration run of the standard shape."""
    if iters < 10:
        raise ValueError(f"run_length_args: iters must be >= 10, got {iters}")
    return [
        "--max-num-iterations", str(iters),
        "--pipeline.model.schedule.pose-init-iters", str(int(iters * shape.pose_init)),
        "--pipeline.model.schedule.static-iters", str(int(iters * shape.static)),
        "--pipeline.model.schedule.dynamic-window-ramp-iters", str(int(iters * shape.window_ramp)),
        "--pipeline.model.schedule.evidence-refresh-iters", str(int(iters * shape.refresh)),
        "--pipeline.model.densify.refine-start-iter", str(max(int(iters * shape.refine_start), 1)),
        "--pipeline.model.densify.refine-stop-iter", str(int(iters * shape.refine_stop)),
    ]


#: Deformation MLP of CPU runs (hidden layers, units, skip layer): the paper's 256x8 costs several
#: times more per step on a CPU and did not fit the demo's 15-minute budget.
CPU_DEFORMATION = (4, 64, 2)
#: Iterations of a CPU run (the demo's length).
CPU_ITERATIONS = 3000


def shape_trainer(config, iters: int, shape: RunShape = RunShape()):
    """``config`` (a nerfstudio TrainerConfig of edygs) with the schedule of an ``iters``-iteration
    run of the standard shape: the same numbers ``run_length_args`` passes on the command line."""
    from dataclasses import replace

    run_length_args(iters, shape)  # validates iters
    model = config.pipeline.model
    schedule = replace(model.schedule, pose_init_iters=int(iters * shape.pose_init), static_iters=int(iters * shape.static),
                       dynamic_window_ramp_iters=int(iters * shape.window_ramp),
                       evidence_refresh_iters=int(iters * shape.refresh))
    densify = replace(model.densify, refine_start_iter=max(int(iters * shape.refine_start), 1),
                      refine_stop_iter=int(iters * shape.refine_stop))
    config.pipeline = replace(config.pipeline, model=replace(model, schedule=schedule, densify=densify))
    config.max_num_iterations = iters
    config.steps_per_save = iters
    return config


def main() -> None:
    if len(sys.argv) != 2 or not sys.argv[1].isdigit():
        raise SystemExit("usage: python -m edygs_ns.configs.run_length ITERS")
    print(" ".join(run_length_args(int(sys.argv[1]))))


if __name__ == "__main__":
    main()

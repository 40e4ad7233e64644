"""Milliseconds per training step on the demo scene, split into parts, per rasteriser backend
(on the CPU; ``--device cuda`` on a GPU).

Usage: ``python benchmarks/train_step.py --out FILE.json [--backends torch cpu] [--threads 1]
[--deform-subset auto|gather|masked] [--device cpu|cuda]``

The scene is the demo's (``edygs-synth`` defaults, seed 0: 128x96, 12 frames x 5 latents),
processed with the true poses (``--poses given``: no COLMAP, same images) into ``--scene-dir``
(reused when there). The run is the demo's CPU shape (64x4 MLP, 3000-iteration run-length
settings) with a short schedule so both phases are reached quickly: ``--static-at`` steps of
pose initialisation, then the static phase, the dynamic phase from ``--dynamic-at``. The loop
is the body of nerfstudio's ``Trainer.train`` (callbacks, ``train_iteration``, callbacks); steps
in ``--static-steps`` and ``--dynamic-steps`` windows are timed.

Parts (wall ms per step, medians): render forward / backward (the rasteriser calls and the
backward of its autograd Functions: projection, compositing), MLP forward (the deformation
field), other forward (the model's remaining forward), losses, other backward (everything in
backward but the rasteriser's: MLP, losses), optimiser (step and schedulers), callbacks
(densification, the phase schedule).

``--deform-subset`` picks how the dynamic phase deforms the Gaussians above the mask threshold
(``EdygsModelConfig.deform_subset``): "gather" (the CPU default) or "masked", the CUDA default
that needs no host round trip (docs/gpu.md, "Host synchronisations"); unset, the config's default.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Callable, Dict, Iterator, List

#: OpenMP threads sleep instead of spinning between parallel regions (set before torch loads).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

from nerfstudio.engine.callbacks import TrainingCallbackLocation  # noqa: E402
from nerfstudio.utils.rich_utils import CONSOLE  # noqa: E402

#: the demo's CPU deformation MLP (scripts/demo.sh).
DEMO_MLP = dict(width=64, depth=4, skip_layer=2)
#: the run length whose settings the demo passes (configs/run_length.py).
DEMO_ITERS = 3000
PARTS = ("render fwd", "render bwd", "MLP fwd", "other fwd", "losses", "other bwd", "optimiser", "callbacks")


class Clock:
    """Accumulates wall seconds per part within the current step."""

    def __init__(self) -> None:
        self.step: Dict[str, float] = defaultdict(float)

    @contextmanager
    def part(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.step[name] += time.perf_counter() - start

    def wrap(self, name: str, fn: Callable) -> Callable:
        def timed(*args, **kwargs):
            with self.part(name):
                return fn(*args, **kwargs)

        return timed


def make_scene(scene_dir: Path) -> Path:
    """The demo's synthetic scene with the true poses, written once (in this process: no console
    scripts needed)."""
    from gpu_check import make_scene as make_check_scene

    return make_check_scene(scene_dir, None, dry=False)


def trainer_for(scene: Path, backend: str, args: argparse.Namespace, output: Path):
    """The demo's CPU run with a short schedule, set up (not trained)."""
    from edygs_ns.configs.method_configs import edygs_trainer_config
    from edygs_ns.configs.run_length import shape_trainer

    config = shape_trainer(edygs_trainer_config(), DEMO_ITERS)
    model = config.pipeline.model
    model = replace(
        model,
        rasterizer=backend,
        deformation=replace(model.deformation, **DEMO_MLP),
        schedule=replace(model.schedule, pose_init_iters=args.static_at, static_iters=args.dynamic_at - args.static_at),
        densify=replace(model.densify, refine_start_iter=args.refine_start),
    )
    if args.deform_subset is not None:
        model = replace(model, deform_subset=args.deform_subset)
    datamanager = replace(config.pipeline.datamanager, dataparser=replace(config.pipeline.datamanager.dataparser, data=scene))
    config.pipeline = replace(config.pipeline, model=model, datamanager=datamanager)
    config.machine.device_type = args.device
    config.max_num_iterations = args.dynamic_steps[1] + 1
    config.vis = "tensorboard"
    config.output_dir = output
    config.timestamp = backend
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def time_steps(trainer, stop: int, clock: Clock, sync: bool = False) -> List[Dict[str, float]]:
    """Run steps 0 .. stop - 1 as nerfstudio's Trainer.train does; per-step part times (ms).
    ``sync``: wait for the GPU at the end of every step, so "total" is the step's GPU time too
    (the parts are then the host's time to queue the work, not the GPU's to do it)."""
    import edygs_ns.model.edygs_model as edygs_model
    from edygs_ns.render import cpu_backend, projection, torch_backend

    real_select = edygs_model.select_backend
    edygs_model.select_backend = lambda *a, **k: clock.wrap("render fwd", real_select(*a, **k))
    for fn_class in (cpu_backend._CompiledRaster, cpu_backend._CompiledProjection, torch_backend._Rasterize,
                     projection._ProjectGaussians):
        fn_class.backward = staticmethod(clock.wrap("render bwd", fn_class.backward))
    model, pipeline = trainer.pipeline.model, trainer.pipeline
    model.deformation.forward = clock.wrap("MLP fwd", model.deformation.forward)
    model.get_outputs = clock.wrap("model fwd", model.get_outputs)
    pipeline.get_train_loss_dict = clock.wrap("fwd + losses", pipeline.get_train_loss_dict)
    trainer.optimizers.optimizer_scaler_step_some = clock.wrap("optimiser", trainer.optimizers.optimizer_scaler_step_some)
    trainer.optimizers.scheduler_step_all = clock.wrap("optimiser", trainer.optimizers.scheduler_step_all)
    steps = []
    for step in range(stop):
        clock.step.clear()
        start = time.perf_counter()
        pipeline.train()
        with clock.part("callbacks"):
            for callback in trainer.callbacks:
                callback.run_callback_at_location(step, location=TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
        with clock.part("iteration"):
            trainer.train_iteration(step)
        with clock.part("callbacks"):
            for callback in trainer.callbacks:
                callback.run_callback_at_location(step, location=TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
        if sync:
            torch.cuda.synchronize()
        total = time.perf_counter() - start
        t = dict(clock.step)
        fwd, model_fwd = t.get("fwd + losses", 0.0), t.get("model fwd", 0.0)
        backward = t.get("iteration", 0.0) - fwd - t.get("optimiser", 0.0)
        parts = {
            "render fwd": t.get("render fwd", 0.0),
            "render bwd": t.get("render bwd", 0.0),
            "MLP fwd": t.get("MLP fwd", 0.0),
            "other fwd": model_fwd - t.get("render fwd", 0.0) - t.get("MLP fwd", 0.0),
            "losses": fwd - model_fwd,
            "other bwd": backward - t.get("render bwd", 0.0),
            "optimiser": t.get("optimiser", 0.0),
            "callbacks": t.get("callbacks", 0.0),
            "total": total,
        }
        steps.append({k: round(1e3 * v, 2) for k, v in parts.items()} | {"step": step,
                     "gaussians": int(model.num_points) if hasattr(model, "num_points") else -1})
    edygs_model.select_backend = real_select
    return steps


def summarise(steps: List[Dict[str, float]], window: List[int]) -> Dict[str, float]:
    """Median of every part over the steps in [window[0], window[1])."""
    chosen = [s for s in steps if window[0] <= s["step"] < window[1]]
    return {k: round(statistics.median(s[k] for s in chosen), 1) for k in (*PARTS, "total", "gaussians")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, help="JSON file for the per-phase medians and every step")
    parser.add_argument("--backends", nargs="+", default=["torch", "cpu"], help="rasterizer config values")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (the demo runs 1)")
    parser.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                        help="training device (cuda: backends auto / gsplat / torch; a sync ends every step)")
    parser.add_argument("--deform-subset", choices=["auto", "gather", "masked"], default=None,
                        help="the model's deform_subset (unset: the config's default)")
    parser.add_argument("--scene-dir", type=Path, default=Path("/tmp/edygs_train_step_scene"))
    parser.add_argument("--static-at", type=int, default=10, help="first step of the static phase")
    parser.add_argument("--dynamic-at", type=int, default=60, help="first step of the dynamic phase")
    parser.add_argument("--refine-start", type=int, default=20, help="first densification step")
    parser.add_argument("--static-steps", type=int, nargs=2, default=[25, 60], help="timed window [a, b)")
    parser.add_argument("--dynamic-steps", type=int, nargs=2, default=[70, 110], help="timed window [a, b)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scene = make_scene(args.scene_dir)
    load = os.getloadavg()
    CONSOLE.log(f"threads={torch.get_num_threads()} load average (1, 5, 15 min)={load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    results = {}
    for backend in args.backends:
        torch.manual_seed(0)
        trainer = trainer_for(scene, backend, args, args.scene_dir / "outputs")
        steps = time_steps(trainer, args.dynamic_steps[1], Clock(), sync=args.device == "cuda")
        results[backend] = {
            "static": summarise(steps, args.static_steps),
            "dynamic": summarise(steps, args.dynamic_steps),
            "load_average": round(os.getloadavg()[0], 2),
            "steps": steps,
        }
        for phase in ("static", "dynamic"):
            row = results[backend][phase]
            CONSOLE.log(f"{backend} {phase}: " + ", ".join(f"{k} {row[k]}" for k in (*PARTS, "total", "gaussians")))
    with open(args.out, "w", encoding="utf-8") as f:
        json.dump({"threads": args.threads, "device": args.device, "deform_subset": args.deform_subset, "results": results},
                  f, indent=1)


if __name__ == "__main__":
    main()

"""No host round trips in an ordinary training step (issue 19 item 3), counted on CPU.

A CUDA step stalls whenever the host reads a device value (``.item()``, ``bool(t)``, ``int(t)``,
``.tolist()``, ``nonzero``, boolean indexing, ``unique``...) or copies host data onto the device
(``torch.tensor(list, device=...)`` synchronises the stream). On the CPU nothing stalls, but the
same calls can be counted: a ``TorchDispatchMode`` sees the ATen ops that need the host
(``_local_scalar_dense`` behind item / bool / int / float, ``nonzero``, boolean ``index``,
``lift_fresh`` behind tensors made from Python data) and ``Tensor.tolist`` / ``numpy`` are
patched. Only calls made while code of ``edygs_ns`` is on the stack count (torch's optimiser and
nerfstudio's trainer are not ours). The step runs the compiled CPU rasteriser, whose Python side
counts too; the torch reference rasteriser's insides would not (host code, never the CUDA
default). On CUDA the step runs gsplat's kernels, whose tile intersection reads one count on the
host (upstream, inside ``isect_tiles``), once per step now that the pair is one call.

Not visible here: copies of tensors made on the CPU onto the device (on the CPU they are no-ops);
those in the step were removed by reading (docs/gpu.md, "Host synchronisations").

Steps with densification, the phase switch, the evidence refresh or logging may synchronise;
the counted steps have none of them.
"""

from __future__ import annotations

import sys
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import List

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).parent))
from train_helpers import make_tiny_scene, tiny_trainer_config  # noqa: E402

import edygs_ns  # noqa: E402
from edygs_ns.model.phases import Phase  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")

PACKAGE = str(Path(edygs_ns.__file__).parent)
#: the torch reference rasteriser's insides: host code by design (gsplat's kernels run on CUDA).
BACKEND_FILES = tuple(str(Path(PACKAGE) / "render" / name) for name in ("torch_backend.py",))
POSE_INIT, STATIC = 2, 6
#: ordinary steps: no switch (step POSE_INIT + STATIC), no densification (refine_start 500),
#: the exposure cache already filled (step 0), no logging (the loop below logs nothing).
STATIC_STEPS = (3, 4, 5)
DYNAMIC_STEPS = (POSE_INIT + STATIC + 1, POSE_INIT + STATIC + 2, POSE_INIT + STATIC + 3)

aten = torch.ops.aten
#: ops whose result the host must wait for (value or data-dependent shape).
READ_OPS = {
    aten._local_scalar_dense.default: "item/bool/int/float",
    aten.nonzero.default: "nonzero",
    aten.masked_select.default: "masked_select",
    aten._unique2.default: "unique",
    aten.unique_consecutive.default: "unique",
    aten.unique_dim.default: "unique",
}
BOOL_INDEX_OPS = (aten.index.Tensor, aten.index_put.default, aten.index_put_.default, aten._index_put_impl_.default)


def _caller() -> str:
    """``file:line`` of the innermost edygs_ns frame on the stack, "" when none (or a backend's inside)."""
    frame = sys._getframe(2)
    while frame is not None:
        name = frame.f_code.co_filename
        if name.startswith(PACKAGE):
            if name.startswith(BACKEND_FILES):
                return ""
            return f"{Path(name).relative_to(PACKAGE)}:{frame.f_lineno}"
        frame = frame.f_back
    return ""


class HostSyncCounter(TorchDispatchMode):
    """Counts host round trips made from edygs_ns code, by kind and place."""

    def __init__(self) -> None:
        super().__init__()
        self.events: List[str] = []

    def record(self, kind: str) -> None:
        where = _caller()
        if where:
            self.events.append(f"{kind} at {where}")

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        kind = READ_OPS.get(func)
        if kind is None and func in BOOL_INDEX_OPS:
            indices = args[1] if len(args) > 1 else kwargs.get("indices", [])
            if any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in indices):
                kind = "boolean index"
        if kind is None and func is aten.repeat_interleave.Tensor and kwargs.get("output_size") is None:
            kind = "repeat_interleave"
        if kind is None and func is aten.lift_fresh.default:
            kind = "tensor from host data"
        if kind is not None:
            self.record(kind)
        return func(*args, **kwargs)


@pytest.fixture(scope="module")
def trainer(tmp_path_factory):
    torch.manual_seed(0)
    root = tmp_path_factory.mktemp("host_sync")
    scene = make_tiny_scene(root, room_init=True)
    config = tiny_trainer_config(scene, root / "runs", iters=DYNAMIC_STEPS[-1] + 1, pose_init=POSE_INIT, static=STATIC)
    # deform every Gaussian, weighted by its mask: the CUDA choice (no nonzero subset)
    config.pipeline.model = replace(config.pipeline.model, deform_subset="masked")
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def _step(trainer, step: int) -> None:
    """One step as nerfstudio's Trainer.train runs it (callbacks, iteration, callbacks), no logging."""
    from nerfstudio.engine.callbacks import TrainingCallbackLocation

    trainer.pipeline.train()
    for callback in trainer.callbacks:
        callback.run_callback_at_location(step, location=TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
    trainer.train_iteration(step)
    for callback in trainer.callbacks:
        callback.run_callback_at_location(step, location=TrainingCallbackLocation.AFTER_TRAIN_ITERATION)


def _counted(trainer, step: int) -> List[str]:
    counter = HostSyncCounter()
    real_tolist, real_numpy = torch.Tensor.tolist, torch.Tensor.numpy

    def tolist(self, *a, **k):
        counter.record("tolist")
        return real_tolist(self, *a, **k)

    def numpy(self, *a, **k):
        counter.record("numpy")
        return real_numpy(self, *a, **k)

    torch.Tensor.tolist, torch.Tensor.numpy = tolist, numpy
    try:
        with counter:
            _step(trainer, step)
    finally:
        torch.Tensor.tolist, torch.Tensor.numpy = real_tolist, real_numpy
    return counter.events


def test_the_counter_sees_host_reads():
    counter = HostSyncCounter()
    x = torch.arange(4.0)
    with counter:
        _ = float(x.sum()), bool((x > 1).any()), torch.nonzero(x), x[x > 1]
        _ = torch.tensor([1.0, 2.0])
    kinds = Counter(e.split(" at ")[0] for e in counter.events)
    # called from tests/, not edygs_ns: nothing counts
    assert not kinds
    from edygs_ns.losses.metrics import ssim

    with counter:
        ssim(torch.rand(1, 16, 16, 3), torch.rand(1, 16, 16, 3))  # reads its result on the host (.item())
    assert counter.events and all("losses/metrics.py" in e for e in counter.events)


def _run_to(trainer, stop: int, counted=()) -> dict:
    """Train up to step ``stop`` (exclusive) from where the module's trainer is; the host round
    trips of the steps in ``counted``, by step. The switch step gets one rigid body when the tiny
    run found none, so the rigid motion is exercised."""
    model = trainer.pipeline.model
    seen = {}
    for step in range(getattr(trainer, "next_step", 0), stop):
        if step in counted:
            seen[step] = _counted(trainer, step)
        else:
            _step(trainer, step)
        if step == POSE_INIT + STATIC and not model.rigid_motion.active:
            n = model.rigid_motion.times.shape[0]
            times = trainer.pipeline.datamanager.train_cameras.times.reshape(-1)
            model.rigid_motion.set(torch.zeros(3), 10.0, 1.0, times, torch.full((n, 3), 0.01), torch.full((n, 3), 0.01))
        trainer.next_step = step + 1
    assert all(not model.config.densify.refine_start_iter <= s for s in seen)  # no densification step counted
    return seen


def _report(seen: dict) -> str:
    return "host round trips per step:\n" + "\n".join(
        f"  step {s}: " + "; ".join(f"{n} x {e}" for e, n in Counter(events).most_common()) for s, events in seen.items()
    )


def test_ordinary_steps_make_no_host_round_trip(trainer):
    model = trainer.pipeline.model
    seen = _run_to(trainer, DYNAMIC_STEPS[-1] + 1, counted=STATIC_STEPS + DYNAMIC_STEPS)
    assert model.phase is Phase.DYNAMIC and model.switched and model.rigid_motion.active
    assert set(seen) == set(STATIC_STEPS + DYNAMIC_STEPS)
    assert not any(seen.values()), _report({s: e for s, e in seen.items() if e})


def test_the_gathered_deformation_reads_the_subset_size_once_per_step(trainer):
    # deform_subset "gather" (the CPU default): one nonzero per step, shared by the pair's cameras
    model = trainer.pipeline.model
    _run_to(trainer, DYNAMIC_STEPS[-1] + 1)
    model.config = replace(model.config, deform_subset="gather")
    try:
        start = trainer.next_step
        seen = _run_to(trainer, start + 2, counted=(start, start + 1))
    finally:
        model.config = replace(model.config, deform_subset="masked")
    for events in seen.values():
        assert len(events) == 1 and events[0].startswith("nonzero at model/edygs_model.py"), _report(seen)

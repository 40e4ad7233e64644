"""The training callback that runs the EDyGS phases by step (``model/phases.py`` says what each holds).

Before every iteration: refuse a resume whose schedule contradicts the checkpoint
(``training/resume.py``), set what trains in the step's phase, make the static -> dynamic switch at
the first dynamic step (motion evidence, seeds, tracks: ``EdygsModel.enter_dynamic_phase``), find
the motion evidence once more at the refresh step, and set the datamanager's time window (the
dynamic phase's curriculum). The model carries these out; this module decides when. Only the
switch and the refresh read device values on the host (once each); every other step decides from
the step number and host flags alone (docs/gpu.md, "Host synchronisations").
"""

from __future__ import annotations

from typing import Any, Callable, Optional, Tuple

from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.engine.optimizers import Optimizers

from edygs_ns.model.edygs_model import EdygsModel
from edygs_ns.model.phases import Phase, phase_at, time_window
from edygs_ns.training.resume import check_resume_phase

#: Sets the datamanager's time window: (lo, hi) normalised times, or None for the whole clip.
TimeWindowSetter = Callable[[Optional[Tuple[float, float]]], None]


class PhaseDriver:
    """Applies the phase schedule of ``model`` at every training step.

    Args:
        model: the EDyGS model (its config holds the schedule).
        optimizers: the trainer's optimizers (densification and seeding edit their state).
        set_time_window: the datamanager's ``set_time_window``, or None when it has none.
    """

    def __init__(self, model: EdygsModel, optimizers: Optimizers, set_time_window: Optional[TimeWindowSetter]) -> None:
        self.model = model
        self.optimizers = optimizers
        self.set_time_window = set_time_window

    def before_step(self, step: int) -> None:
        """Bring the model to training step ``step`` (0-based)."""
        model, schedule = self.model, self.model.config.schedule
        model.begin_step(step, self.optimizers.optimizers)
        check_resume_phase(step, schedule, switched=model.switched)  # a changed schedule on --load-dir
        phase = phase_at(step, schedule)
        model.apply_phase(phase)
        if phase is Phase.DYNAMIC and model.config.use_motion_mask and not model.switched:
            model.enter_dynamic_phase()
        if step == schedule.refresh_step and model.seeding_active:
            model.refresh_motion()
        if self.set_time_window is not None and model.seeding_active:
            self.set_time_window(time_window(step, schedule, model.config.seeding.reference_time))

    def callback(self) -> TrainingCallback:
        """The callback that runs :meth:`before_step` before every training iteration."""
        return TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], self.before_step)


def attach_phase_driver(model: Any, datamanager: Any, optimizers: Optimizers) -> Optional[PhaseDriver]:
    """Give an EDyGS model its training data and a phase driver; None for any other model."""
    if not isinstance(model, EdygsModel):
        return None
    model.bind_training_data(datamanager.train_dataset.cameras, getattr(datamanager, "train_image", None))
    return PhaseDriver(model, optimizers, getattr(datamanager, "set_time_window", None))

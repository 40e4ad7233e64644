"""The EDyGS pipeline: nerfstudio's vanilla pipeline plus the phase driver's training callback."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional, Type

from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig

from edygs_ns.training.phase_driver import PhaseDriver, attach_phase_driver


@dataclass
class EdygsPipelineConfig(VanillaPipelineConfig):
    """nerfstudio's vanilla pipeline; training runs the EDyGS phases by step."""

    _target: Type = field(default_factory=lambda: EdygsPipeline)


class EdygsPipeline(VanillaPipeline):
    """VanillaPipeline whose training callbacks start with the phase driver (training/phase_driver.py)."""

    phase_driver: Optional[PhaseDriver] = None

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        self.phase_driver = attach_phase_driver(self.model, self.datamanager, training_callback_attributes.optimizers)
        callbacks = super().get_training_callbacks(training_callback_attributes)
        return ([self.phase_driver.callback()] if self.phase_driver is not None else []) + callbacks

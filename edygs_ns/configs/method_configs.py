"""nerfstudio method entry points: `edygs` and the blurry-input deformable-3DGS baseline `edygs-blurry`.

One factory builds the trainer config; variants are ``dataclasses.replace`` of its parts.
Paper ablations (Table 2) are one flag: ``--pipeline.model.ablation {events-only,edi-only,
edi-events,edi-events-pose,paper,full}`` (``paper``: EDyGS without our blur loss).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Dict, Literal, Optional, Tuple

from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.plugins.types import MethodSpecification
from tyro.conf import Suppress

from edygs_ns.compat import allow_nerfstudio_checkpoints
from edygs_ns.configs.run_length import CPU_DEFORMATION, CPU_ITERATIONS, shape_trainer
from edygs_ns.data.datamanager import EdygsDataManagerConfig
from edygs_ns.data.dataparser import EdygsDataParserConfig
from edygs_ns.model.edygs_model import EdygsModelConfig
from edygs_ns.model import ns_export_mask
from edygs_ns.model.gaussians import GAUSSIAN_ATTRIBUTES
from edygs_ns.model.phases import CAMERA_GROUP, DEFORMATION_GROUP, MASK_GROUP, RIGID_GROUP, PhaseSchedule
from edygs_ns.training.pipeline import EdygsPipelineConfig

allow_nerfstudio_checkpoints()
ns_export_mask.install()  # ns-export gaussian-splat PLYs get the motion_mask column

#: full-scale defaults (GPU); the CPU demo passes smaller numbers on the command line.
MAX_ITERATIONS = 20000
POSE_INIT_ITERS = 1000
STATIC_ITERS = 4000


# The optimiser and scheduler configs of every parameter group, with the settings EDyGS never
# changes hidden from ``ns-train --help`` (a class docstring would print once per group there).
@dataclass
class AdamConfig(AdamOptimizerConfig):
    # Adam with eps 1e-15, no gradient clipping and no weight decay.
    eps: Suppress[float] = 1e-15
    max_norm: Suppress[Optional[float]] = None
    weight_decay: Suppress[float] = 0


@dataclass
class DecayConfig(ExponentialDecaySchedulerConfig):
    # Exponential decay of the learning rate to lr_final at max_steps, without warm-up.
    lr_pre_warmup: Suppress[float] = 1e-8
    warmup_steps: Suppress[int] = 0
    ramp: Suppress[Literal["linear", "cosine"]] = "cosine"


def _adam(lr: float, lr_final: float | None = None, max_steps: int = MAX_ITERATIONS) -> dict:
    scheduler = None if lr_final is None else DecayConfig(lr_final=lr_final, max_steps=max_steps)
    return {"optimizer": AdamConfig(lr=lr), "scheduler": scheduler}


#: Adam learning rate per parameter group: (initial, final of an exponential decay or None for constant).
LEARNING_RATES: Dict[str, Tuple[float, Optional[float]]] = {
    "means": (1.6e-4, 1.6e-6),
    "features_dc": (0.0025, None),
    "features_rest": (0.0025 / 20, None),
    "opacities": (0.05, None),
    "scales": (0.005, None),
    "quats": (0.001, None),
    MASK_GROUP: (0.005, None),
    DEFORMATION_GROUP: (8e-4, 1.6e-6),
    RIGID_GROUP: (1e-3, None),
    CAMERA_GROUP: (1e-4, 1e-6),
}
#: the parameter groups: one per Gaussian attribute, then the deformation MLP, the rigid motions and the poses.
PARAMETER_GROUPS: Tuple[str, ...] = GAUSSIAN_ATTRIBUTES + (DEFORMATION_GROUP, RIGID_GROUP, CAMERA_GROUP)


def optimizer_configs(max_steps: int = MAX_ITERATIONS) -> dict:
    """One entry per parameter group (PARAMETER_GROUPS, learning rates from LEARNING_RATES).

    Raises:
        KeyError: a parameter group has no learning rate.
    """
    return {name: _adam(*LEARNING_RATES[name], max_steps=max_steps) for name in PARAMETER_GROUPS}


def edygs_trainer_config(method_name: str = "edygs") -> TrainerConfig:
    """The full EDyGS trainer config."""
    return TrainerConfig(
        method_name=method_name,
        steps_per_eval_image=500,
        steps_per_eval_batch=0,
        steps_per_save=2000,
        steps_per_eval_all_images=1_000_000,
        max_num_iterations=MAX_ITERATIONS,
        mixed_precision=False,
        pipeline=EdygsPipelineConfig(
            datamanager=EdygsDataManagerConfig(dataparser=EdygsDataParserConfig()),
            model=EdygsModelConfig(schedule=PhaseSchedule(pose_init_iters=POSE_INIT_ITERS, static_iters=STATIC_ITERS)),
        ),
        optimizers=optimizer_configs(),
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    )


def blurry_baseline_config() -> TrainerConfig:
    """Deformable 3DGS on the blurry frames at the exposure-centre time: no events, no EDI, no mask."""
    base = edygs_trainer_config("edygs-blurry")
    datamanager = replace(
        base.pipeline.datamanager,
        pair_events=False,
        dataparser=replace(base.pipeline.datamanager.dataparser, image_source="blurry"),
    )
    model = replace(base.pipeline.model, ablation="blurry")
    base.pipeline = replace(base.pipeline, datamanager=datamanager, model=model)
    return base


def cpu_variant(config: TrainerConfig) -> TrainerConfig:
    """``config`` made for a CPU: the demo's 3000-iteration run shape, a 64x4 deformation MLP."""
    config = shape_trainer(config, CPU_ITERATIONS)
    depth, width, skip = CPU_DEFORMATION
    deformation = replace(config.pipeline.model.deformation, depth=depth, width=width, skip_layer=skip)
    config.pipeline = replace(config.pipeline, model=replace(config.pipeline.model, deformation=deformation))
    config.method_name = f"{config.method_name}-cpu"
    config.machine.device_type = "cpu"
    return config


edygs_method = MethodSpecification(
    config=edygs_trainer_config(),
    description="EDyGS: sharp dynamic 3D Gaussians from a blurry monocular video and events",
)

blurry_baseline_method = MethodSpecification(
    config=blurry_baseline_config(),
    description="Baseline: deformable 3D Gaussians trained on the blurry frames (no events)",
)

edygs_cpu_method = MethodSpecification(
    config=cpu_variant(edygs_trainer_config()),
    description="EDyGS sized for a CPU: 3000 iterations, 64x4 deformation MLP (the demo's settings)",
)

blurry_baseline_cpu_method = MethodSpecification(
    config=cpu_variant(blurry_baseline_config()),
    description="The blurry-input baseline sized for a CPU (3000 iterations, 64x4 deformation MLP)",
)

"""Shared set-up for the training tests: a tiny synthetic scene and a small EDyGS trainer config."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from nerfstudio.engine.trainer import TrainerConfig

from edygs_ns.configs.method_configs import edygs_trainer_config
from edygs_ns.model.deformation import DeformationConfig
from edygs_ns.scripts.synth import SynthConfig, write_synthetic_scene
from edygs_ns.training.schedule import PhaseSchedule

#: tiny scene: 48x36 pixels, 4 blurry frames, k = 5 -> 20 latents.
TINY_SCENE = dict(width=48, height=36, n_frames=4, k=5, sim_steps_per_exposure=12, novel_stride=2)
#: small deformation MLP to keep CPU tests quick.
TINY_DEFORMATION = DeformationConfig(depth=4, width=32, skip_layer=2, xyz_frequencies=4, time_frequencies=3)


def make_tiny_scene(root: Path) -> Path:
    """Raw capture -> processed scene with the true poses (no COLMAP); returns the scene folder."""
    from edygs_ns.scripts.process import ProcessConfig, process

    raw = write_synthetic_scene(SynthConfig(output_dir=root / "raw", **TINY_SCENE))
    config = ProcessConfig(output=root / "scene", poses="given", num_random_points=2000)
    config.inputs.exposures = raw / "exposures.csv"
    config.inputs.events = raw / "events.h5"
    process(config)
    return root / "scene"


def tiny_trainer_config(scene: Path, output: Path, iters: int, pose_init: int, static: int) -> TrainerConfig:
    """The real `edygs` method config, made small: CPU, no viewer, short phases."""
    config = edygs_trainer_config()
    model = replace(
        config.pipeline.model,
        schedule=PhaseSchedule(pose_init_iters=pose_init, static_iters=static),
        deformation=TINY_DEFORMATION,
        sh_degree=1,
    )
    datamanager = replace(config.pipeline.datamanager, dataparser=replace(config.pipeline.datamanager.dataparser, data=scene))
    config.pipeline = replace(config.pipeline, model=model, datamanager=datamanager)
    config.machine.device_type = "cpu"
    config.max_num_iterations = iters
    config.steps_per_save = iters
    config.save_only_latest_checkpoint = False
    config.vis = "tensorboard"
    config.output_dir = output
    config.timestamp = "test"
    config.steps_per_eval_image = 1_000_000
    config.steps_per_eval_batch = 0
    config.steps_per_eval_all_images = 1_000_000
    return config

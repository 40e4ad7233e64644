"""Shared set-up for the training tests: a tiny synthetic scene and a small EDyGS trainer config."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from nerfstudio.engine.trainer import TrainerConfig

from edygs_ns.configs.method_configs import edygs_trainer_config
from edygs_ns.model.deformation import DeformationConfig
from edygs_ns.sim.writer import SynthConfig, write_synthetic_scene
from edygs_ns.model.phases import PhaseSchedule

#: tiny scene: 48x36 pixels, 4 blurry frames, k = 5 -> 20 latents.
TINY_SCENE = dict(width=48, height=36, n_frames=4, k=5, sim_steps_per_exposure=12, novel_stride=2)
#: small deformation MLP to keep CPU tests quick.
TINY_DEFORMATION = DeformationConfig(depth=4, width=32, skip_layer=2, xyz_frequencies=4, time_frequencies=3)


def room_points(config: SynthConfig, count: int = 4000, seed: int = 0):
    """``count`` points on the static surfaces of the synthetic room (world frame, the true poses'
    frame) with their shaded texture colours: [P, 3] float xyz, [P, 3] uint8 rgb. Stands in for
    the sparse points a pose-and-structure step would give, so a short test run starts from a
    sensible static model."""
    from edygs_ns.sim.writer import build_world

    scene = build_world(config).scene
    rng = np.random.default_rng(seed)
    area = np.array([np.linalg.norm(np.cross(q.edge_u, q.edge_v)) for q in scene.quads])
    ids = rng.choice(len(scene.quads), size=count, p=area / area.sum())
    a, b = rng.uniform(size=count), rng.uniform(size=count)
    stack = scene.quad_stack
    xyz = stack.origins[ids] + a[:, None] * stack.edges_u[ids] + b[:, None] * stack.edges_v[ids]
    rgb = scene.atlas.sample(ids, a, b) * scene.quad_shading[ids][:, None]
    return xyz, np.rint(np.clip(rgb, 0.0, 1.0) * 255).astype(np.uint8)


def make_tiny_scene(root: Path, room_init: bool = False, **overrides) -> Path:
    """Raw capture -> processed scene with the true poses (no COLMAP); returns the scene folder.
    ``overrides``: SynthConfig fields changed from TINY_SCENE (e.g. preset="two-objects");
    ``room_init``: initial points on the room's surfaces instead of random ones."""
    from edygs_ns.io.ply import write_ply_points
    from edygs_ns.preprocess.writer import PLY_NAME
    from edygs_ns.preprocess.pipeline import ProcessConfig, process

    synth = SynthConfig(output_dir=root / "raw", **{**TINY_SCENE, **overrides})
    raw = write_synthetic_scene(synth)
    config = ProcessConfig(output=root / "scene", poses="given", num_random_points=2000)
    config.inputs.exposures = raw / "exposures.csv"
    config.inputs.events = raw / "events.h5"
    process(config)
    if room_init:
        write_ply_points(root / "scene" / PLY_NAME, *room_points(synth))
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

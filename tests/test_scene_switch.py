"""The static -> dynamic switch on the scene suite's presets: objects found apart, nothing added
when nothing moves, a deforming object ends up with moving Gaussians (tiny scenes, true poses)."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from train_helpers import make_tiny_scene, tiny_trainer_config  # noqa: E402

from edygs_ns.model.phases import Phase  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")

#: a little larger than the training tests' scene, so each object covers a few dozen pixels
SIZE = dict(width=96, height=72, n_frames=6, k=5, sim_steps_per_exposure=12)
POSE_INIT, STATIC = 100, 300


def _train_through_switch(preset: str, root: Path, dynamic_steps: int = 1, **seeding):
    torch.manual_seed(0)  # the same training whichever tests ran before in this process
    scene = make_tiny_scene(root / "data", room_init=True, preset=preset, **SIZE)
    config = tiny_trainer_config(scene, root / "runs", iters=POSE_INIT + STATIC + dynamic_steps, pose_init=POSE_INIT, static=STATIC)
    model_config = config.pipeline.model
    config.pipeline.model = replace(model_config, seeding=replace(model_config.seeding, **seeding))
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()
    model = trainer.pipeline.model
    assert model.phase is Phase.DYNAMIC and model.static_masks.numel() > 0
    return model


def _movers(model) -> int:
    return int((model.rigid_motion.reach > 0).sum())


def test_two_objects_get_a_body_each(tmp_path):
    model = _train_through_switch("two-objects", tmp_path)
    assert _movers(model) == 2
    centres = model.rigid_motion.centre[model.rigid_motion.reach > 0]
    assert float((centres[0] - centres[1]).norm()) > 0.3  # world units: two places, not one object split


def test_nothing_moves_nothing_is_added(tmp_path):
    torch.manual_seed(0)
    scene = make_tiny_scene(tmp_path / "data", room_init=True, preset="static", **SIZE)
    config = tiny_trainer_config(scene, tmp_path / "runs", iters=POSE_INIT + STATIC, pose_init=POSE_INIT, static=STATIC)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()  # pose-init and static phases only
    model = trainer.pipeline.model
    before = model.num_points
    model.train()
    trainer.pipeline.phase_driver.before_step(POSE_INIT + STATIC)  # the switch
    assert model.phase is Phase.DYNAMIC and model.static_masks.numel() > 0
    assert _movers(model) == 0 and not model.rigid_motion.active
    assert model.num_points == before  # no dynamic seeds
    assert float(model.static_masks.float().sum()) == 0.0  # M̂ asks the mask to stay at 0 everywhere
    model.refresh_motion()  # the evidence found again later in the dynamic phase: still nothing
    assert _movers(model) == 0 and model.num_points == before
    assert float(model.static_masks.float().sum()) == 0.0


def test_the_refresh_finds_an_object_the_switch_missed(tmp_path):
    # the switch tracks one region only, so one of the two balls is missed there
    model = _train_through_switch("two-objects", tmp_path, dynamic_steps=30, max_candidates=1)
    assert _movers(model) == 1
    first = model.rigid_motion.centre[0].clone()
    before, claimed = model.num_points, float(model.static_masks.float().sum())
    model.refresh_motion()
    assert _movers(model) == 2 and model.num_points > before
    assert float((model.rigid_motion.centre[1] - first).norm()) > 0.3  # the other ball, not the first again
    assert float(model.static_masks.float().sum()) > claimed  # M̂ now asks for the new object's mask


def test_a_deforming_object_ends_up_with_moving_gaussians(tmp_path):
    model = _train_through_switch("deforming", tmp_path, dynamic_steps=30)
    assert _movers(model) >= 1
    with torch.no_grad():
        start = model.deformed_gaussians(0.0, deform=True)["means"]
        end = model.deformed_gaussians(1.0, deform=True)["means"]
    dynamic = torch.sigmoid(model.gauss_params["mask_logit"]).squeeze(-1) > 0.5
    travel = (end - start).norm(dim=-1)
    assert int(dynamic.sum()) >= 20
    # the dynamic Gaussians travel; the static ones stay where they are
    assert float(travel[dynamic].median()) > 10 * float(travel[~dynamic].median()) + 1e-4

"""Co-visibility of novel-view pixels from the training views (true geometry of the simulator)."""

from __future__ import annotations

import json

import numpy as np
from PIL import Image

from edygs_ns.sim.covisibility import covisible_counts
from edygs_ns.sim.writer import SynthConfig, build_world, write_synthetic_scene


def _world(preset: str = "static"):
    return build_world(SynthConfig(output_dir="unused", width=48, height=36, n_frames=2, preset=preset))


def test_a_view_sees_itself_and_a_sideways_move_loses_one_edge():
    world = _world()
    pose = world.c2w(0)
    counts = covisible_counts(world.scene, world.camera, pose, [], [pose, pose], [[], []])
    assert (counts == 2).all()  # every pixel of the room is seen by both copies of the view
    moved = pose.copy()
    moved[:3, 3] += 0.3 * pose[:3, 0]  # the training camera 0.3 units to the right
    counts = covisible_counts(world.scene, world.camera, pose, [], [moved], [[]])
    left, right = counts[:, :4].mean(), counts[:, -4:].mean()
    assert left < 0.5 and right > 0.8  # the left edge left the moved frustum; the right one stayed (but for disocclusions)
    behind = pose.copy()
    behind[:3, :3] = pose[:3, :3] @ np.diag([-1.0, 1.0, -1.0])  # turned around
    assert covisible_counts(world.scene, world.camera, pose, [], [behind], [[]]).sum() == 0


def test_an_object_hides_what_is_behind_it():
    world = _world("rigid")
    t = int(world.timeline.latents[0, 0])
    pose = world.c2w(t)
    posed = world.posed(t)
    alone = covisible_counts(world.scene, world.camera, pose, [], [pose], [posed])
    _, instance = world.render(t)
    assert instance.any()
    # the room behind the sphere is not seen by a view in which the sphere stands in front of it
    assert alone[instance > 0].mean() < 0.2 and alone[instance == 0].mean() > 0.95


def test_the_synthetic_scene_writes_novel_covisibility(tmp_path):
    folder = write_synthetic_scene(SynthConfig(output_dir=tmp_path / "scene", width=48, height=36, n_frames=2, k=3,
                                               sim_steps_per_exposure=6, preset="static"))
    meta = json.loads((folder / "gt" / "transforms.json").read_text())
    for frame in meta["novel_frames"]:
        counts = np.asarray(Image.open(folder / "gt" / frame["covisible_path"]))
        assert counts.shape == (36, 48) and counts.max() <= len(meta["frames"])
        assert 0.5 < (counts > 0).mean() < 1.0  # most pixels were seen, an edge off the path was not

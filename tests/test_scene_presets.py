"""The scene suite of edygs-synth (edygs_ns.sim.presets, shapes, motions) on tiny scenes."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Callable, Dict, List

import h5py
import numpy as np
import pytest
from PIL import Image
from scipy import ndimage

from edygs_ns.scripts.synth import entrypoint
from edygs_ns.sim.writer import SynthConfig, SynthWorld, build_world, write_synthetic_scene
from edygs_ns.sim.appearance import TextureAtlas
from edygs_ns.sim.motions import ArmSegmentMotion, SquashStretchMotion
from edygs_ns.sim.presets import SCENE_PRESETS, MovingObject
from edygs_ns.sim.scene import render
from edygs_ns.sim.shapes import Box, Ellipsoid, ObjectState
from edygs_ns.sim.trajectory import ObjectMotion, axis_angle_matrix

WIDTH, HEIGHT, N_FRAMES, K = 48, 36, 3, 3
#: Latent name at normalised time 0.5 (exposure 1 of [0, 80] ms, [100, 180] ms, [200, 280] ms).
MIDDLE = f"{N_FRAMES // 2:04d}_{K // 2}.png"
FIRST, LAST = "0000_0.png", f"{N_FRAMES - 1:04d}_{K - 1}.png"


def tiny_config(out: Path, preset: str, **changes) -> SynthConfig:
    base = SynthConfig(output_dir=out, width=WIDTH, height=HEIGHT, n_frames=N_FRAMES, k=K, n_subframes=3,
                       sim_steps_per_exposure=4, novel_stride=2, preset=preset)
    return dataclasses.replace(base, **changes)


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Callable[[str], Path]:
    """capture(preset) writes that preset's tiny scene once per module and returns its folder."""
    root = tmp_path_factory.mktemp("presets")
    written: Dict[str, Path] = {}

    def get(preset: str) -> Path:
        if preset not in written:
            written[preset] = write_synthetic_scene(tiny_config(root / preset, preset))
        return written[preset]
    return get


def load(folder: Path, sub: str, name: str) -> np.ndarray:
    return np.asarray(Image.open(folder / "gt" / sub / name))


def world_of(folder: Path, preset: str) -> SynthWorld:
    return build_world(tiny_config(folder, preset))


def at_tau(world: SynthWorld, tau: float) -> int:
    return int(round(tau * world.timeline.duration_us))


def load_events(folder: Path) -> Dict[str, np.ndarray]:
    with h5py.File(folder / "events.h5", "r") as f:
        return {name: f[name][:] for name in ("x", "y", "t", "p")}


def principal_angle(mask: np.ndarray) -> float:
    """Image angle (radians, in [0, pi)) of the long axis of a binary region."""
    ys, xs = np.nonzero(mask)
    cov = np.cov(np.stack([xs, -ys]).astype(float))
    w, v = np.linalg.eigh(cov)
    long_axis = v[:, np.argmax(w)]
    return float(np.arctan2(long_axis[1], long_axis[0]) % np.pi)


def elongation(mask: np.ndarray) -> float:
    """sqrt of the ratio of the region's second-moment eigenvalues (1 for a disc)."""
    ys, xs = np.nonzero(mask)
    w = np.linalg.eigvalsh(np.cov(np.stack([xs, ys]).astype(float)))
    return float(np.sqrt(w[1] / w[0]))


@pytest.mark.parametrize("preset", SCENE_PRESETS)
def test_every_preset_writes_a_valid_capture(capture, preset: str) -> None:
    folder = capture(preset)
    meta = json.loads((folder / "gt" / "transforms.json").read_text())
    scene = json.loads((folder / "scene.json").read_text())
    assert scene["preset"] == preset and scene["config"]["preset"] == preset
    n_objects = len(scene["objects"])
    assert [o["id"] for o in scene["objects"]] == list(range(1, n_objects + 1))
    assert (n_objects == 0) == (preset == "static")
    assert all(o["shape"] in ("ellipsoid", "box") and "motion" in o for o in scene["objects"])
    assert len(meta["frames"]) == N_FRAMES * K and len(meta["novel_frames"]) == len(range(0, N_FRAMES, 2))
    assert len(list((folder / "frames").glob("*.png"))) == N_FRAMES
    assert scene["n_events"] > 0
    seen = set()
    for record in meta["frames"] + meta["novel_frames"]:
        instance = np.asarray(Image.open(folder / "gt" / record["instance_path"]))
        mask = np.asarray(Image.open(folder / "gt" / record["mask_path"]))
        rgb = np.asarray(Image.open(folder / "gt" / record["file_path"]))
        assert instance.shape == mask.shape == (HEIGHT, WIDTH) and instance.dtype == np.uint8
        assert rgb.shape == (HEIGHT, WIDTH, 3)
        assert np.array_equal(mask > 0, instance > 0), "mask is the union of the objects"
        assert instance.max() <= n_objects
        seen |= set(np.unique(instance).tolist())
    assert seen - {0} == set(range(1, n_objects + 1)), "every object shows up somewhere"
    assert record["instance_path"].startswith("novel_instance/")


def test_static_has_no_mask_and_only_camera_events(capture, tmp_path: Path) -> None:
    folder = capture("static")
    for sub in ("instance", "novel_instance", "mask", "novel_mask"):
        assert all(not np.asarray(Image.open(p)).any() for p in (folder / "gt" / sub).glob("*.png"))
    moving = load_events(folder)
    assert len(moving["t"]) > 1000
    still = write_synthetic_scene(tiny_config(tmp_path / "still", "static", camera_speed=0.0, camera_dolly=0.0))
    assert len(load_events(still)["t"]) == 0, "nothing moves, nothing fires"
    # The rigid scene of the same seed fires the same events wherever its sphere never comes.
    rigid = world_of(capture("rigid"), "rigid")
    touched = np.zeros((HEIGHT, WIDTH), dtype=bool)
    for t in rigid.timeline.sim_times:
        touched |= rigid.render(int(t))[1] > 0
    touched = ndimage.binary_dilation(touched, iterations=2)
    assert 0.0 < touched.mean() < 0.6
    other = load_events(capture("rigid"))

    def away(ev: Dict[str, np.ndarray]) -> np.ndarray:
        keep = ~touched[ev["y"], ev["x"]]
        rows = np.stack([ev[k][keep].astype(np.int64) for k in ("t", "y", "x", "p")], axis=1)
        return rows[np.lexsort(rows.T[::-1])]
    assert np.array_equal(away(moving), away(other))
    assert len(other["t"]) > len(moving["t"]), "the sphere adds events"


@pytest.mark.parametrize("preset,count", [("two-objects", 2), ("three-objects", 3)])
def test_independent_objects_apart_at_middle(capture, preset: str, count: int) -> None:
    folder = capture(preset)
    mask = load(folder, "mask", MIDDLE) > 0
    instance = load(folder, "instance", MIDDLE)
    _, n_components = ndimage.label(mask)
    assert n_components == count
    for obj_id in range(1, count + 1):
        labels, n = ndimage.label(instance == obj_id)
        assert n == 1, f"object {obj_id} is one region"
    world = world_of(folder, preset)
    t_mid = at_tau(world, 0.5)
    c2w = world.c2w(t_mid)
    depths = sorted(float(-(c2w[:3, :3].T @ (o.state(t_mid / 1e6).centre - c2w[:3, 3]))[2]) for o in world.objects)
    assert np.min(np.diff(depths)) > 0.4, "different depths"
    assert {type(o.shape) for o in world.objects} == {Ellipsoid, Box}
    assert all(isinstance(o.motion, type(world.objects[0].motion)) for o in world.objects)
    states = [[o.state(at_tau(world, tau) / 1e6) for o in world.objects] for tau in (0.0, 1.0)]
    for start, end in zip(*states):
        assert np.linalg.norm(end.centre - start.centre) > 0.5 and not np.allclose(end.rotation, start.rotation)


def test_two_objects_cross_in_the_image(capture) -> None:
    world = world_of(capture("two-objects"), "two-objects")

    def image_x(obj: MovingObject, tau: float) -> float:
        t = at_tau(world, tau)
        c2w = world.c2w(t)
        local = c2w[:3, :3].T @ (obj.state(t / 1e6).centre - c2w[:3, 3])
        return float(local[0] / -local[2])
    order = [np.sign(image_x(world.objects[0], tau) - image_x(world.objects[1], tau)) for tau in (0.0, 0.5)]
    assert order[0] == -order[1], "they swap sides"
    # Where the paths cross, the nearer sphere hides part of the box; at mid-clip none of it.
    box = world.objects[1]
    hidden = []
    for tau in np.linspace(0.0, 0.5, 11):
        t = at_tau(world, tau)
        alone = render(world.scene, world.camera, world.c2w(t), [(box.shape, box.state(t / 1e6))], world.supersample)
        hidden.append(1.0 - (world.render(t)[1] == 2).sum() / (alone[1] == 1).sum())
    assert max(hidden) > 0.3 and hidden[-1] == 0.0, hidden


def test_articulated_arm_bends_at_the_elbow(capture) -> None:
    folder = capture("articulated")
    world = world_of(folder, "articulated")
    assert [type(o.motion) for o in world.objects] == [ArmSegmentMotion, ArmSegmentMotion]
    arm = world.objects[0].motion.arm
    relative = []
    for t in world.timeline.latents.ravel():
        upper, lower = (o.state(t / 1e6) for o in world.objects)
        # hinged: the upper segment's tip is the lower segment's root
        tip = upper.centre + 0.5 * arm.lengths[0] * upper.rotation[:, 0]
        assert np.allclose(tip, lower.centre - 0.5 * arm.lengths[1] * lower.rotation[:, 0], atol=1e-9)
        instance = world.render(int(t))[1]
        assert set(np.unique(instance)) == {0, 1, 2}
        assert (ndimage.binary_dilation(instance == 1) & (instance == 2)).any(), "segments meet at the elbow"
        relative.append(principal_angle(instance == 2) - principal_angle(instance == 1))
    # Largest change of the (undirected, so modulo pi) image angle between the segments.
    change = np.subtract.outer(relative, relative)
    change = np.abs((change + 0.5 * np.pi) % np.pi - 0.5 * np.pi)
    assert np.degrees(change.max()) > 30.0, f"elbow angle in the image barely changes: {np.degrees(relative)}"
    shoulders = {tuple(np.round(o.motion.arm.shoulder, 12)) for o in world.objects}
    assert len(shoulders) == 1
    assert np.ptp([arm.joint_angles(t / 1e6)[1] for t in world.timeline.latents.ravel()]) > np.radians(30.0)


def _elongations(world: SynthWorld) -> List[float]:
    return [elongation(world.render(int(t))[1] > 0) for t in world.timeline.latents.ravel()]


def test_deforming_changes_shape_at_constant_volume(tmp_path: Path) -> None:
    # Twice the tiny size so the silhouette's shape is measurable.
    world = build_world(tiny_config(tmp_path, "deforming", width=2 * WIDTH, height=2 * HEIGHT))
    (obj,) = world.objects
    assert isinstance(obj.motion, SquashStretchMotion)
    scales = np.array([obj.state(t / 1e6).scale for t in world.timeline.latents.ravel()])
    assert np.allclose(np.prod(scales, axis=1), 1.0), "volume kept"
    assert scales[:, 0].max() / scales[:, 0].min() > 1.3
    deforming = _elongations(world)
    rigid = _elongations(build_world(tiny_config(tmp_path, "rigid", width=2 * WIDTH, height=2 * HEIGHT)))
    assert max(rigid) < 1.1, "a rigid sphere stays round"
    assert max(deforming) / min(deforming) > 1.2, f"silhouette shape barely changes: {deforming}"


def test_enter_leave_outside_at_one_end(capture) -> None:
    folder = capture("enter-leave")
    ends = [load(folder, "mask", name).any() for name in (FIRST, LAST)]
    assert ends.count(False) == 1
    assert load(folder, "mask", MIDDLE).any()
    scene = json.loads((folder / "scene.json").read_text())
    assert scene["objects"][0]["name"] == "sphere"
    for seed in (1, 2, 3):
        world = build_world(tiny_config(folder, "enter-leave", seed=seed))
        visible = [world.render(at_tau(world, tau))[1].any() for tau in (0.0, 0.5, 1.0)]
        assert visible[1] and visible[0] != visible[2], f"seed {seed}: {visible}"


def test_large_covers_a_quarter(capture) -> None:
    folder = capture("large")
    assert (load(folder, "mask", MIDDLE) > 0).mean() >= 0.25
    coverage = [(load(folder, "mask", f"{p:04d}_{j}.png") > 0).mean() for p in range(N_FRAMES) for j in range(K)]
    assert np.mean(np.array(coverage) >= 0.25) > 0.5
    assert np.mean(coverage) < 0.4, "about a third of the pixels, not most of them"
    for name in ("two-objects", "articulated", "deforming"):
        mid = (load(capture(name), "mask", MIDDLE) > 0).mean()
        assert 0.03 < mid < 0.2, f"{name} covers {mid:.3f}"


def test_rigid_is_the_default_single_sphere(tmp_path: Path) -> None:
    assert SynthConfig().preset == "rigid"
    world = build_world(tiny_config(tmp_path, "rigid", motion="linear"))
    (obj,) = world.objects
    assert isinstance(obj.motion, ObjectMotion) and obj.motion.kind == "linear"
    assert isinstance(obj.shape, Ellipsoid) and np.all(obj.shape.radii == SynthConfig.object_radius)
    # The sphere shortcut (the original ray caster's arithmetic) and the general ellipsoid route,
    # forced by a unit scale, render the same view.
    t = int(world.timeline.latents[1, 1])
    pose = obj.state(t / 1e6)
    assert pose.scale is None
    rgb, instance = render(world.scene, world.camera, world.c2w(t), [(obj.shape, pose)], world.supersample)
    general = dataclasses.replace(pose, scale=np.ones(3))
    rgb_g, instance_g = render(world.scene, world.camera, world.c2w(t), [(obj.shape, general)], world.supersample)
    assert instance.any() and np.array_equal(instance, instance_g)
    assert np.abs(rgb - rgb_g).max() < 1e-4


def test_same_seed_same_scene_other_seed_different() -> None:
    for preset in SCENE_PRESETS:
        first, again, other = (build_world(tiny_config(Path("unused"), preset, seed=seed)) for seed in (0, 0, 1))
        describe = [[o.describe() for o in w.objects] for w in (first, again, other)]
        assert describe[0] == describe[1]
        assert preset == "static" or describe[0] != describe[2]


def test_cli_preset(tmp_path: Path, monkeypatch) -> None:
    out = tmp_path / "cli"
    argv = ["edygs-synth", "--output-dir", str(out), "--width", "32", "--height", "24", "--n-frames", "2",
            "--sim-steps-per-exposure", "4", "--preset", "two-objects", "--seed", "1"]
    monkeypatch.setattr(sys, "argv", argv)
    entrypoint()
    scene = json.loads((out / "scene.json").read_text())
    assert scene["preset"] == "two-objects" and [o["shape"] for o in scene["objects"]] == ["ellipsoid", "box"]
    with pytest.raises(ValueError, match="preset"):
        build_world(tiny_config(tmp_path, "nonsense"))


# ----------------------------------------------------------------------------------------------
# Shapes against closed forms
# ----------------------------------------------------------------------------------------------

TEXTURE = np.full((4, 8, 3), 0.5, dtype=np.float32)


def rays_at(target: np.ndarray, origin: np.ndarray) -> np.ndarray:
    d = np.asarray(target, float) - origin
    return (d / np.linalg.norm(d, axis=-1, keepdims=True)).astype(np.float32)


def test_ellipsoid_hits_along_its_axes_and_deforms() -> None:
    rot = axis_angle_matrix(np.array([0.3, 1.0, 0.2]), 0.7)
    centre = np.array([0.5, -0.2, -3.0])
    shape = Ellipsoid(np.array([0.6, 0.3, 0.2]), TEXTURE)
    origin = np.array([0.1, 0.3, 2.0])
    pose = ObjectState(centre, rot)
    # Points on the surface along each local axis, seen from the origin: the hit is there (or nearer).
    for axis, radius in enumerate(shape.radii):
        surface = centre + radius * rot[:, axis]
        t = shape.intersect(pose, origin, rays_at(surface[None], origin))[0]
        assert t <= np.linalg.norm(surface - origin) + 1e-5
    t_centre = shape.intersect(pose, origin, rays_at(centre[None], origin))[0]
    dist = np.linalg.norm(centre - origin)
    assert dist - 0.6 - 1e-6 <= t_centre <= dist - 0.2 + 1e-6
    assert np.isinf(shape.intersect(pose, origin, rays_at(centre[None] + [[0.0, 2.0, 0.0]], origin))[0])
    # A scale equals an ellipsoid with the scaled radii.
    scale = np.array([1.4, 0.8, 1.0 / 1.12])
    dirs = rays_at(centre + np.random.default_rng(0).uniform(-0.5, 0.5, (200, 3)), origin)
    scaled = shape.intersect(ObjectState(centre, rot, scale), origin, dirs)
    direct = Ellipsoid(shape.radii * scale, TEXTURE).intersect(pose, origin, dirs)
    assert np.isfinite(scaled).sum() > 50
    assert np.array_equal(np.isfinite(scaled), np.isfinite(direct))
    assert np.allclose(scaled[np.isfinite(scaled)], direct[np.isfinite(direct)])


def test_box_slab_method() -> None:
    faces = TextureAtlas.from_textures([TEXTURE] * 6)
    box = Box(np.array([0.5, 0.25, 0.1]), faces)
    origin = np.zeros(3)
    # Axis-aligned, straight ahead: the front face is half_size[2] in front of the centre.
    pose = ObjectState(np.array([0.0, 0.0, -3.0]), np.eye(3))
    dirs = rays_at(np.array([[0.0, 0.0, -1.0], [0.45, 0.2, -3.0], [0.55, 0.0, -3.0], [0.0, 0.3, -3.0]]), origin)
    t = box.intersect(pose, origin, dirs)
    assert np.isclose(t[0], 2.9) and np.isfinite(t[1]) and np.isinf(t[2]) and np.isinf(t[3])
    # Turning the box and the rays together changes nothing.
    rot = axis_angle_matrix(np.array([1.0, 2.0, 0.5]), 1.1)
    centre = np.array([0.2, -0.1, -2.5])
    local_targets = np.random.default_rng(1).uniform(-0.6, 0.6, (300, 3))
    dirs_a = rays_at(local_targets + centre, origin)
    t_a = box.intersect(ObjectState(centre, np.eye(3)), origin, dirs_a)
    eye = np.array([0.0, 0.0, 0.0])
    origin_b = centre + rot @ (eye - centre)
    dirs_b = (dirs_a.astype(float) @ rot.T).astype(np.float32)
    t_b = box.intersect(ObjectState(centre, rot), origin_b, dirs_b)
    assert np.isfinite(t_a).sum() > 50
    assert np.array_equal(np.isfinite(t_a), np.isfinite(t_b))
    assert np.allclose(t_a[np.isfinite(t_a)], t_b[np.isfinite(t_b)], atol=1e-5)
    # Shading: a face squarely towards the light is brighter than one away from it.
    hit = np.isfinite(t_a)
    colour = box.radiance(ObjectState(centre, np.eye(3)), origin, dirs_a[hit], t_a[hit])
    assert colour.shape == (hit.sum(), 3) and np.all(colour > 0) and np.all(colour <= 1)

"""The scene suite of `edygs-synth`: named presets of moving objects in the built-in room.

A preset is a list of MovingObjects (a shape from edygs_ns.sim.shapes and a motion from
edygs_ns.sim.motions or edygs_ns.sim.trajectory), deterministic from two random streams: one for
textures (the scene stream, continued after the room) and one for motions. Presets:

- ``rigid``: one textured sphere moving linear / circular / bouncing (``--motion``), exactly the
  scene edygs-synth wrote before the suite existed.
- ``two-objects``: a sphere and a turning box at different depths, moving in opposite directions;
  their image paths cross early in the clip, they are apart at mid-clip.
- ``three-objects``: a sphere, a box and an ellipsoid at three depths, apart at mid-clip.
- ``articulated``: a two-segment arm; the upper segment swings about a fixed shoulder, the lower
  one about the elbow at its tip with its own angle. Each segment is an object of its own
  (instance ids 1 = upper, 2 = lower).
- ``deforming``: an ellipsoid squashing and stretching at constant volume while it rocks and moves.
- ``enter-leave``: a sphere outside the image at one end of the clip (entering at the start or
  leaving at the end), in view at mid-clip.
- ``large``: a large ellipsoid covering about a third of the image.
- ``static``: no moving object.

Instance ids are 1 + the object's position in the preset's list (0 = static). Except for
``rigid``, objects are placed relative to the true camera at mid-clip (a given image position and
depth at tau = 0.5), so the mid-clip layout holds for any seed and clip length; whole paths are
then shifted, if needed, to stay inside the room and out of its static boxes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Literal, Sequence, Tuple, get_args

import numpy as np

from edygs_ns.sim.motions import ArmMotion, ArmSegmentMotion, LinearMotion, Motion, SquashStretchMotion
from edygs_ns.sim.scene import ROOM_MAX, ROOM_MIN, PinholeCamera, StaticBox
from edygs_ns.sim.shapes import Ellipsoid, ObjectState, Shape, bounding_radius, textured_box, textured_ellipsoid
from edygs_ns.sim.trajectory import WORLD_UP, CameraPath, axis_angle_matrix, make_object_motion

ScenePreset = Literal["rigid", "two-objects", "three-objects", "articulated", "deforming", "enter-leave", "large",
                      "static"]
#: Names of the scene presets, in the order of the suite.
SCENE_PRESETS: Tuple[str, ...] = get_args(ScenePreset)

#: Normalised clip time at which presets lay their objects out relative to the camera.
MID_CLIP = 0.5
#: Gap kept between a moving object and the room's walls or the static boxes, world units.
CLEARANCE = 0.05
#: Instants (evenly spaced over the clip) at which paths are checked against the room and boxes.
CHECK_SAMPLES = 33
#: Spheres along an ellipsoid's long axis that stand in for it in the clearance checks.
PROXY_SPHERES = 7
#: A path that meets a static box is moved up (then sideways) in steps of NUDGE_STEP, at most
#: MAX_NUDGE world units.
NUDGE_STEP = 0.02
MAX_NUDGE = 1.0
#: Relative jitter the seed applies to each object's size and to each travel component.
SIZE_JITTER = 0.05
TRAVEL_JITTER = 0.1


@dataclass(frozen=True)
class PresetContext:
    """What a preset's layout depends on besides its random streams.

    Attributes:
        camera_path: the true camera over time (objects are placed where it sees them).
        camera: intrinsics (the field of view decides what is outside the image).
        duration_s: clip length, seconds.
        motion: the rigid preset's path kind (linear, circular, bouncing).
        speed: the rigid preset's sphere speed, world units per second.
        radius: the rigid preset's sphere radius, world units.
        obstacles: static boxes the moving objects must not enter (the rigid preset ignores them,
            as edygs-synth always did).
    """

    camera_path: CameraPath
    camera: PinholeCamera
    duration_s: float
    motion: str
    speed: float
    radius: float
    obstacles: Tuple[StaticBox, ...] = ()

    def view_point(self, tau: float, u: float, v: float, depth: float) -> np.ndarray:
        """[3] world point ``depth`` in front of the camera at clip time ``tau``, seen at tangent-
        plane image position (u, v) (u = x / depth to the right, v = y / depth upwards)."""
        c2w = self.camera_path.c2w(tau * self.duration_s)
        return c2w[:3, 3] + c2w[:3, :3] @ np.array([u * depth, v * depth, -depth])


@dataclass(frozen=True)
class MovingObject:
    """A moving shape: what it looks like and how it moves.

    Attributes:
        name: short label recorded in scene.json ("sphere", "box", "upper_arm", ...).
        shape: geometry and texture (edygs_ns.sim.shapes).
        motion: pose over time (anything with ``state(t_s) -> ObjectState``).
    """

    name: str
    shape: Shape
    motion: Motion

    def state(self, t_s: float) -> ObjectState:
        """Pose at ``t_s`` seconds."""
        return self.motion.state(t_s)

    def describe(self) -> Dict[str, Any]:
        """JSON-ready name, shape and motion parameters."""
        return {"name": self.name, **self.shape.describe(), "motion": _jsonable(self.motion)}


def _jsonable(value: Any) -> Any:
    """Dataclasses (with their type name), arrays and tuples as plain JSON values."""
    if dataclasses.is_dataclass(value):
        fields = {f.name: _jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
        return {"type": type(value).__name__, **fields}
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (tuple, list)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


@dataclass(frozen=True)
class MoverSpec:
    """One rigidly moving object of a preset, placed where the camera sees it at mid-clip.

    Attributes:
        shape: "ellipsoid" (size = semi-axes) or "box" (size = full extents).
        size: world units.
        view: (u, v) tangent-plane image position at mid-clip (u = x / depth right, v up).
        depth: distance in front of the camera at mid-clip, world units.
        travel: world displacement over the whole clip, world units.
        spin: radians the object turns over the clip, about an axis drawn from the seed.
    """

    shape: str
    size: Tuple[float, float, float]
    view: Tuple[float, float]
    depth: float
    travel: Tuple[float, float, float]
    spin: float


#: two-objects: a near sphere and a far box passing each other (image paths cross at tau ~ 0.15).
#: Depths and heights keep the movers in front of or above the static boxes for most seeds.
TWO_OBJECTS = (
    MoverSpec("ellipsoid", (0.32, 0.32, 0.32), (0.17, 0.03), 2.5, (1.2, 0.2, 0.0), 3.0),
    MoverSpec("box", (0.5, 0.42, 0.42), (-0.17, 0.0), 3.1, (-1.4, -0.15, 0.0), 1.6),
)
#: three-objects: near sphere, middle box, far ellipsoid, spread across the image at mid-clip.
THREE_OBJECTS = (
    MoverSpec("ellipsoid", (0.28, 0.28, 0.28), (-0.27, 0.1), 2.5, (1.3, -0.15, 0.0), 3.0),
    MoverSpec("box", (0.45, 0.4, 0.4), (0.0, -0.13), 3.0, (-0.6, 0.35, 0.0), 1.8),
    MoverSpec("ellipsoid", (0.34, 0.28, 0.28), (0.27, 0.14), 3.8, (-1.2, 0.1, 0.0), 2.5),
)
#: large: one big, slowly drifting and turning ellipsoid in front of the camera (about a third of
#: the pixels at 128x96; at 1.14x this size, ~44 %, COLMAP's frame followed the mover, docs/experiments.md).
LARGE = (MoverSpec("ellipsoid", (0.88, 0.75, 0.63), (-0.15, 0.0), 2.6, (0.5, 0.1, 0.0), 1.2),)

#: deforming: rest semi-axes, placement, travel and steady turn (about the viewing axis).
DEFORMING = MoverSpec("ellipsoid", (0.46, 0.38, 0.36), (0.05, 0.0), 2.9, (-0.9, 0.15, 0.0), 1.2)
#: deforming: log-amplitudes and cycles over the clip of the local x and y scale oscillations.
DEFORM_STRETCH = (0.35, 0.2)
DEFORM_CYCLES = (1.5, 1.0)
#: deforming: amplitude (radians) and cycles of the rocking about the viewing axis.
DEFORM_WOBBLE = 0.35
DEFORM_WOBBLE_CYCLES = 2.0

#: articulated: shoulder placement, segment lengths (shoulder-elbow, elbow-tip), segment
#: thickness (semi-axis) and how far each segment's ellipsoid reaches past its joints.
ARM_VIEW = (-0.18, 0.26)
ARM_DEPTH = 3.0
ARM_LENGTHS = (0.85, 0.75)
ARM_THICKNESS = 0.17
ARM_JOINT_OVERLAP = 0.12
#: articulated: (shoulder, elbow) mean angles, swing amplitudes (degrees) and swings per clip.
ARM_REST_DEG = (-55.0, 45.0)
ARM_AMPLITUDE_DEG = (30.0, 50.0)
ARM_CYCLES = (0.75, 1.25)
#: articulated: largest yaw (radians) of the swing plane away from facing the camera.
ARM_MAX_YAW = 0.3
#: articulated: the seed scales each swing amplitude by a factor in [1 - this, 1].
ARM_AMPLITUDE_JITTER = 0.15

#: enter-leave: sphere radius, image position and depth at mid-clip, and the gap (world units)
#: between the sphere and the edge of the view at the end where it is outside the image.
ENTER_LEAVE_RADIUS = 0.3
ENTER_LEAVE_VIEW = (0.2, 0.05)
ENTER_LEAVE_DEPTH = 2.1
ENTER_LEAVE_GAP = 0.05
#: enter-leave: turn of the sphere as a fraction of rolling (distance / radius).
ENTER_LEAVE_ROLL = 0.5


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    return axis_angle_matrix(_unit(rng.normal(size=3)), rng.uniform(0.0, 2.0 * np.pi))


def _jittered(rng: np.random.Generator, values: Sequence[float], share: float) -> np.ndarray:
    return np.asarray(values, float) * rng.uniform(1.0 - share, 1.0 + share, size=len(values))


def _room_shift(centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """[3] smallest translation keeping spheres (centres [M, 3], radii [M]) inside the room."""
    margin = radii[:, None] + CLEARANCE
    low = np.max(np.asarray(ROOM_MIN) + margin - centres, axis=0)  # shift must be >= low
    high = np.min(np.asarray(ROOM_MAX) - margin - centres, axis=0)  # and <= high
    return np.where(low <= high, np.clip(0.0, low, high), 0.5 * (low + high))


def _proxy_spheres(shape: Shape, pose: ObjectState) -> Tuple[np.ndarray, np.ndarray]:
    """Spheres (centres [P, 3], radii [P]) that together hold the posed shape: a box's bounding
    sphere; for an ellipsoid, spheres of its middle semi-axis along its longest axis (their
    capsule holds the ellipsoid)."""
    if not isinstance(shape, Ellipsoid):
        return pose.centre[None, :], np.array([bounding_radius(shape, pose)])
    radii = np.asarray(shape.radii, float) * (1.0 if pose.scale is None else np.asarray(pose.scale, float))
    order = np.argsort(radii)
    long_axis = np.asarray(pose.rotation, float)[:, order[2]]
    reach = radii[order[2]] - radii[order[1]]
    offsets = np.linspace(-reach, reach, PROXY_SPHERES)
    return pose.centre + offsets[:, None] * long_axis, np.full(PROXY_SPHERES, radii[order[1]])


def _sampled_proxies(movers: Sequence[Tuple[Shape, Motion]], duration_s: float) -> Tuple[np.ndarray, np.ndarray]:
    """Proxy spheres of every mover at CHECK_SAMPLES instants over the clip, concatenated."""
    parts = [_proxy_spheres(shape, motion.state(t)) for shape, motion in movers
             for t in np.linspace(0.0, duration_s, CHECK_SAMPLES)]
    return np.concatenate([c for c, _ in parts]), np.concatenate([r for _, r in parts])


def _clear(centres: np.ndarray, radii: np.ndarray, obstacles: Sequence[StaticBox]) -> bool:
    """Whether the spheres stay CLEARANCE away from every static box."""
    return all(np.all(box.distance(centres) >= radii + CLEARANCE) for box in obstacles)


def _placement_shift(movers: Sequence[Tuple[Shape, Motion]], context: PresetContext,
                     sideways: bool = True) -> np.ndarray:
    """[3] translation of the movers' paths that keeps them in the room and out of the static
    boxes: the smallest one into the room, plus the smallest lift clear of the boxes (or, if no
    lift up to MAX_NUDGE clears them and ``sideways``, the smallest sideways move)."""
    centres, radii = _sampled_proxies(movers, context.duration_s)
    base = _room_shift(centres, radii)
    directions = [np.asarray(WORLD_UP, float)] + ([np.array([-1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])]
                                                  if sideways else [])
    steps = np.arange(0.0, MAX_NUDGE + 0.5 * NUDGE_STEP, NUDGE_STEP)
    for group in (directions[:1], directions[1:]):
        for step in steps:
            for direction in group:
                shift = base + step * direction
                in_room = not np.any(_room_shift(centres + shift, radii))
                if in_room and _clear(centres + shift, radii, context.obstacles):
                    return shift
    return base


def _shifted(motion: LinearMotion, shape: Shape, context: PresetContext) -> LinearMotion:
    """``motion`` translated to stay in the room and out of the static boxes."""
    return dataclasses.replace(motion, anchor=motion.anchor + _placement_shift([(shape, motion)], context))


def _make_shape(spec: MoverSpec, texture_rng: np.random.Generator, size: np.ndarray) -> Shape:
    if spec.shape == "ellipsoid":
        return textured_ellipsoid(texture_rng, size)
    if spec.shape == "box":
        return textured_box(texture_rng, size)
    raise ValueError(f"MoverSpec.shape must be 'ellipsoid' or 'box', got {spec.shape!r}")


def _name(shape: str, size: np.ndarray) -> str:
    return "sphere" if shape == "ellipsoid" and np.all(size == size[0]) else shape


def _linear_mover(spec: MoverSpec, side: float, texture_rng: np.random.Generator, motion_rng: np.random.Generator,
                  context: PresetContext) -> MovingObject:
    """A MoverSpec made real; ``side`` = -1 mirrors it left-right."""
    size = np.asarray(spec.size, float) * motion_rng.uniform(1.0 - SIZE_JITTER, 1.0 + SIZE_JITTER)
    travel = _jittered(motion_rng, spec.travel, TRAVEL_JITTER) * np.array([side, 1.0, 1.0])
    anchor = context.view_point(MID_CLIP, side * spec.view[0], spec.view[1], spec.depth)
    shape = _make_shape(spec, texture_rng, size)
    motion = LinearMotion(anchor, MID_CLIP, travel, _random_rotation(motion_rng), _unit(motion_rng.normal(size=3)),
                          float(spec.spin), context.duration_s)
    return MovingObject(_name(spec.shape, size), shape, _shifted(motion, shape, context))


def _movers(specs: Sequence[MoverSpec], mirror: bool = True) -> Callable[..., List[MovingObject]]:
    """A preset of rigid movers; with ``mirror`` the seed may mirror the layout left-right."""
    def build(texture_rng: np.random.Generator, motion_rng: np.random.Generator,
              context: PresetContext) -> List[MovingObject]:
        side = float(motion_rng.choice([-1.0, 1.0])) if mirror else 1.0
        return [_linear_mover(spec, side, texture_rng, motion_rng, context) for spec in specs]
    return build


def _rigid(texture_rng: np.random.Generator, motion_rng: np.random.Generator,
           context: PresetContext) -> List[MovingObject]:
    """The original scene's sphere: texture first from the scene stream, path from the object stream."""
    shape = textured_ellipsoid(texture_rng, [context.radius] * 3)
    motion = make_object_motion(motion_rng, context.motion, context.speed, context.radius)
    return [MovingObject("sphere", shape, motion)]


def _deforming(texture_rng: np.random.Generator, motion_rng: np.random.Generator,
               context: PresetContext) -> List[MovingObject]:
    side = float(motion_rng.choice([-1.0, 1.0]))
    spec = DEFORMING
    view_axis = -context.camera_path.c2w(MID_CLIP * context.duration_s)[:3, 2]  # camera forward at mid-clip
    base = axis_angle_matrix(view_axis, motion_rng.uniform(0.0, 2.0 * np.pi))  # long axis in the image plane
    path = LinearMotion(context.view_point(MID_CLIP, side * spec.view[0], spec.view[1], spec.depth), MID_CLIP,
                        _jittered(motion_rng, spec.travel, TRAVEL_JITTER) * np.array([side, 1.0, 1.0]), base,
                        view_axis, side * spec.spin, context.duration_s)
    shape = textured_ellipsoid(texture_rng, spec.size)
    phases = tuple(motion_rng.uniform(0.0, 2.0 * np.pi, size=3))
    motion = SquashStretchMotion(path, DEFORM_STRETCH, DEFORM_CYCLES, phases[:2], DEFORM_WOBBLE, DEFORM_WOBBLE_CYCLES,
                                 phases[2], view_axis)
    path = dataclasses.replace(path, anchor=path.anchor + _placement_shift([(shape, motion)], context))
    return [MovingObject("ellipsoid", shape, dataclasses.replace(motion, path=path))]


def _articulated(texture_rng: np.random.Generator, motion_rng: np.random.Generator,
                 context: PresetContext) -> List[MovingObject]:
    side = float(motion_rng.choice([-1.0, 1.0]))
    up = np.asarray(WORLD_UP, float)
    yaw = axis_angle_matrix(up, motion_rng.uniform(-ARM_MAX_YAW, ARM_MAX_YAW))
    plane_u, plane_v = side * (yaw @ np.array([1.0, 0.0, 0.0])), up
    arm = ArmMotion(
        shoulder=context.view_point(MID_CLIP, side * ARM_VIEW[0], ARM_VIEW[1], ARM_DEPTH),
        plane_u=plane_u, plane_v=plane_v, lengths=ARM_LENGTHS,
        rest_angles=tuple(np.radians(ARM_REST_DEG)),
        amplitudes=tuple(np.radians(ARM_AMPLITUDE_DEG) * motion_rng.uniform(1.0 - ARM_AMPLITUDE_JITTER, 1.0, size=2)),
        cycles=ARM_CYCLES, phases=tuple(motion_rng.uniform(0.0, 2.0 * np.pi, size=2)),
        duration_s=context.duration_s,
    )
    shapes = [textured_ellipsoid(texture_rng, [0.5 * length + ARM_JOINT_OVERLAP, ARM_THICKNESS, ARM_THICKNESS])
              for length in ARM_LENGTHS]
    shift = _placement_shift([(shape, ArmSegmentMotion(arm, i)) for i, shape in enumerate(shapes)], context)
    arm = dataclasses.replace(arm, shoulder=arm.shoulder + shift)
    return [MovingObject(name, shape, ArmSegmentMotion(arm, i))
            for i, (name, shape) in enumerate(zip(("upper_arm", "lower_arm"), shapes))]


def _enter_leave(texture_rng: np.random.Generator, motion_rng: np.random.Generator,
                 context: PresetContext) -> List[MovingObject]:
    """A sphere crossing the side of the view: outside the image at tau_out (0: it enters, 1: it
    leaves), at ENTER_LEAVE_VIEW at mid-clip. Its side is the one that keeps it in the room."""
    tau_out = float(motion_rng.choice([0.0, 1.0]))
    r, depth = ENTER_LEAVE_RADIUS, ENTER_LEAVE_DEPTH
    tan_half = context.camera.cx / context.camera.fl_x
    half_fov = np.arctan(tan_half)
    u_out = tan_half + (r / np.cos(half_fov) + ENTER_LEAVE_GAP) / depth  # sphere wholly past the frustum side
    shape = textured_ellipsoid(texture_rng, [r] * 3)
    candidates = []
    for side in (1.0, -1.0):
        anchor = context.view_point(MID_CLIP, side * ENTER_LEAVE_VIEW[0], ENTER_LEAVE_VIEW[1], depth)
        outside = context.view_point(tau_out, side * u_out, ENTER_LEAVE_VIEW[1], depth)
        travel = (outside - anchor) / (tau_out - MID_CLIP)
        motion = LinearMotion(anchor, MID_CLIP, travel, _random_rotation(motion_rng), _unit(motion_rng.normal(size=3)),
                              ENTER_LEAVE_ROLL * float(np.linalg.norm(travel)) / r, context.duration_s)
        shift = _placement_shift([(shape, motion)], context, sideways=False)
        candidates.append((float(np.abs(shift).sum()), motion_rng.uniform(), motion, shift))
    _, _, motion, shift = min(candidates, key=lambda c: c[:2])
    return [MovingObject("sphere", shape, dataclasses.replace(motion, anchor=motion.anchor + shift))]


def _static(texture_rng: np.random.Generator, motion_rng: np.random.Generator,
            context: PresetContext) -> List[MovingObject]:
    return []


_BUILDERS: Dict[str, Callable[..., List[MovingObject]]] = {
    "rigid": _rigid,
    "two-objects": _movers(TWO_OBJECTS),
    "three-objects": _movers(THREE_OBJECTS),
    "articulated": _articulated,
    "deforming": _deforming,
    "enter-leave": _enter_leave,
    "large": _movers(LARGE, mirror=False),
    "static": _static,
}


def build_objects(preset: str, texture_rng: np.random.Generator, motion_rng: np.random.Generator,
                  context: PresetContext) -> Tuple[MovingObject, ...]:
    """The moving objects of ``preset`` (instance id of objects[i] is i + 1).

    Args:
        preset: one of SCENE_PRESETS.
        texture_rng: source of the objects' textures (edygs-synth continues the room's stream).
        motion_rng: source of sizes, paths, turns and phases.
        context: the camera, clip length and the rigid preset's sphere settings.

    Raises:
        ValueError: unknown preset.
    """
    if preset not in _BUILDERS:
        raise ValueError(f"build_objects: preset must be one of {SCENE_PRESETS}, got {preset!r}")
    return tuple(_BUILDERS[preset](texture_rng, motion_rng, context))

"""Where things are and when: the camera path, the rigid preset's sphere motion, the exposure timeline.

Times are microseconds (int64) on the clip's clock; motion functions take seconds (float).
Poses are camera-to-world 4x4 matrices in the OpenGL convention (x right, y up, looking down -z).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Sequence, Tuple

import numpy as np

from edygs_ns.sim.scene import ROOM_MIN
from edygs_ns.sim.shapes import ObjectState

MotionKind = Literal["linear", "circular", "bouncing"]
#: The object motions write_synthetic_scene understands.
MOTION_KINDS: Tuple[str, ...] = ("linear", "circular", "bouncing")

#: World up direction used by look_at.
WORLD_UP = (0.0, 1.0, 0.0)
#: Point the camera looks at when it is at CAMERA_CENTRE, world units.
CAMERA_TARGET = (0.0, -0.25, -2.0)
#: Share of the camera's offset from CAMERA_CENTRE that its look-at point follows: 0 keeps the
#: look-at point fixed (large rotations, parallax cancelled at the target), 1 keeps the
#: orientation fixed (pure translation). In between, the view turns by a few degrees.
CAMERA_TARGET_FOLLOW = 0.7
#: Centre of the camera's elliptic sweep, world units.
CAMERA_CENTRE = (0.0, 0.05, 1.5)
#: Vertical half-height of the camera ellipse as a fraction of its lateral half-width.
CAMERA_LIFT_RATIO = 0.4
#: Microseconds per second.
US_PER_S = 1_000_000

#: Centre of the moving object's region of motion, world units.
OBJECT_CENTRE = (0.0, -0.2, -2.0)
#: Half-length of the linear back-and-forth segment, world units.
LINEAR_HALF_LENGTH = 0.9
#: Largest elevation / depth tilt (radians) the seed gives the linear segment.
LINEAR_MAX_TILT = 0.35
#: Radius of the circular path, world units.
CIRCLE_RADIUS = 0.7
#: Largest tilt (radians) of the circle's plane away from facing the camera.
CIRCLE_MAX_TILT = 0.5
#: Bouncing: half-width of the horizontal range, the bounce height, and the share of the
#: object speed that is horizontal (the vertical peak speed at floor contact is the full speed).
BOUNCE_HALF_WIDTH = 0.9
BOUNCE_HEIGHT = 1.0
BOUNCE_HORIZONTAL_SHARE = 0.6
#: Largest depth jitter (world units) the seed gives the bouncing plane.
BOUNCE_DEPTH_JITTER = 0.3
#: Texture spin rate of the object, as a fraction of rolling (speed / radius).
SPIN_SHARE = 0.5


def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = WORLD_UP) -> np.ndarray:
    """Camera-to-world [4, 4] (OpenGL: camera -z points from eye to target, +y roughly ``up``)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    forward = target - eye
    norm = np.linalg.norm(forward)
    if norm == 0.0:
        raise ValueError("look_at: eye and target coincide")
    forward /= norm
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to up")
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, -forward, eye
    return c2w


def axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """[3, 3] rotation by ``angle`` radians about the unit vector ``axis`` (Rodrigues)."""
    x, y, z = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


@dataclass(frozen=True)
class CameraPath:
    """A smooth camera sweep: an ellipse facing the scene and a slow dolly forward, aimed at a
    look-at point that follows the camera part of the way (so the view turns by a few degrees).

    Attributes:
        sway: lateral half-width of the ellipse, world units.
        speed: approximate speed of the camera centre along the ellipse, world units per second.
        dolly: total forward (-z) travel over the clip, world units.
        duration_s: clip length in seconds (the dolly is spread over it).
        phase: starting angle on the ellipse, radians.
        direction: +1 or -1, sense of travel.
    """

    sway: float
    speed: float
    dolly: float
    duration_s: float
    phase: float
    direction: float

    @property
    def angular_rate(self) -> float:
        """Radians per second on the ellipse (speed over the RMS radius)."""
        lift = CAMERA_LIFT_RATIO * self.sway
        return self.speed / max(np.sqrt(0.5 * (self.sway**2 + lift**2)), 1e-12)

    def position(self, t_s: float, widen: float = 0.0) -> np.ndarray:
        """[3] camera centre at ``t_s`` seconds.

        Args:
            t_s: time in seconds.
            widen: world units added to both half-axes of the ellipse (0: the training path;
                > 0: a concentric, wider ellipse, about ``widen`` away from the training path).
        """
        angle = self.phase + self.direction * self.angular_rate * t_s
        offset = np.array([
            (self.sway + widen) * np.sin(angle),
            (CAMERA_LIFT_RATIO * self.sway + widen) * np.cos(angle),
            -self.dolly * t_s / max(self.duration_s, 1e-12),
        ])
        return np.asarray(CAMERA_CENTRE, float) + offset

    def target(self, t_s: float) -> np.ndarray:
        """[3] point the camera looks at, at ``t_s`` seconds."""
        offset = self.position(t_s) - np.asarray(CAMERA_CENTRE, float)
        return np.asarray(CAMERA_TARGET, float) + CAMERA_TARGET_FOLLOW * offset

    def c2w(self, t_s: float) -> np.ndarray:
        """[4, 4] camera-to-world at ``t_s`` seconds."""
        return look_at(self.position(t_s), self.target(t_s))

    def novel_c2w(self, t_s: float, offset: float) -> np.ndarray:
        """[4, 4] a view off the training path: the training orientation at ``t_s``, the camera
        centre moved outward (sideways and up or down) onto the ellipse widened by ``offset``."""
        c2w = self.c2w(t_s)
        c2w[:3, 3] = self.position(t_s, widen=offset)
        return c2w


def make_camera_path(rng: np.random.Generator, sway: float, speed: float, dolly: float, duration_s: float) -> CameraPath:
    """A camera path whose starting point and sense of travel come from ``rng``."""
    if sway < 0 or speed < 0:
        raise ValueError(f"make_camera_path: sway ({sway}) and speed ({speed}) must be >= 0")
    return CameraPath(sway, speed, dolly, duration_s, float(rng.uniform(0.0, 2.0 * np.pi)),
                      float(rng.choice([-1.0, 1.0])))


@dataclass(frozen=True)
class ObjectMotion:
    """Motion of the moving sphere; every variant is smooth except the bounce itself.

    Attributes:
        kind: "linear" (sinusoidal back and forth along a segment, peak speed = speed),
            "circular" (constant speed on a tilted circle) or "bouncing" (ballistic-looking
            hops along the floor, reflecting off the ends of its horizontal range).
        speed: world units per second (see kind).
        radius: object radius, world units (sets the floor contact height and the spin).
        axis_a: [3] unit vector, first in-plane direction of the motion.
        axis_b: [3] unit vector, second in-plane direction (circle only).
        centre: [3] centre of the motion, world units.
        phase: phase of the motion, radians.
        spin_axis: [3] unit axis of the texture spin.
    """

    kind: str
    speed: float
    radius: float
    axis_a: np.ndarray
    axis_b: np.ndarray
    centre: np.ndarray
    phase: float
    spin_axis: np.ndarray

    def centre_at(self, t_s: float) -> np.ndarray:
        """[3] object centre at ``t_s`` seconds."""
        if self.kind == "linear":
            omega = self.speed / LINEAR_HALF_LENGTH
            return self.centre + LINEAR_HALF_LENGTH * np.sin(omega * t_s + self.phase) * self.axis_a
        if self.kind == "circular":
            angle = self.speed / CIRCLE_RADIUS * t_s + self.phase
            return self.centre + CIRCLE_RADIUS * (np.cos(angle) * self.axis_a + np.sin(angle) * self.axis_b)
        # bouncing: triangle wave across the range, |sin| hops above the floor
        horizontal = BOUNCE_HORIZONTAL_SHARE * self.speed
        span = 2.0 * BOUNCE_HALF_WIDTH
        s = (horizontal * t_s + self.phase / (2.0 * np.pi) * 2.0 * span) % (2.0 * span)
        x = -BOUNCE_HALF_WIDTH + (s if s <= span else 2.0 * span - s)
        hop_period = np.pi * BOUNCE_HEIGHT / max(self.speed, 1e-12)
        height = BOUNCE_HEIGHT * abs(np.sin(np.pi * t_s / hop_period + self.phase))
        floor = ROOM_MIN[1] + self.radius
        return np.array([self.centre[0] + x, floor + height, self.centre[2]])

    def state(self, t_s: float) -> ObjectState:
        """Object pose (centre and spin) at ``t_s`` seconds."""
        spin = SPIN_SHARE * self.speed / self.radius * t_s
        return ObjectState(self.centre_at(t_s), axis_angle_matrix(self.spin_axis, spin))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def make_object_motion(rng: np.random.Generator, kind: str, speed: float, radius: float) -> ObjectMotion:
    """An ObjectMotion of ``kind`` whose direction, tilt, phase and spin axis come from ``rng``."""
    if kind not in MOTION_KINDS:
        raise ValueError(f"make_object_motion: kind must be one of {MOTION_KINDS}, got {kind!r}")
    if speed < 0:
        raise ValueError(f"make_object_motion: speed must be >= 0, got {speed}")
    centre = np.asarray(OBJECT_CENTRE, float).copy()
    phase = float(rng.uniform(0.0, 2.0 * np.pi))
    spin_axis = _unit(rng.normal(size=3))
    if kind == "linear":
        elevation, depth = rng.uniform(-LINEAR_MAX_TILT, LINEAR_MAX_TILT, size=2)
        axis_a = _unit(np.array([1.0, np.tan(elevation), np.tan(depth)]))
        axis_b = np.zeros(3)
    elif kind == "circular":
        tilt = rng.uniform(-CIRCLE_MAX_TILT, CIRCLE_MAX_TILT)
        axis_a = np.array([1.0, 0.0, 0.0])
        axis_b = np.array([0.0, np.cos(tilt), np.sin(tilt)])
    else:
        centre[2] += rng.uniform(-BOUNCE_DEPTH_JITTER, BOUNCE_DEPTH_JITTER)
        axis_a, axis_b = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    return ObjectMotion(kind, float(speed), float(radius), axis_a, axis_b, centre, phase, spin_axis)


@dataclass(frozen=True)
class Timeline:
    """All instants of a clip, integer microseconds.

    Attributes:
        exposure_start: [n] start of exposure p.
        exposure_end: [n] end of exposure p.
        latents: [n, k] latent instants (first = exposure start, last = exposure end).
        subframes: [n, S] sharp sub-frame instants averaged into blurry frame p.
        sim_times: [T] sorted unique instants fed to the event simulator (covers the clip and
            contains every latent and sub-frame instant).
    """

    exposure_start: np.ndarray
    exposure_end: np.ndarray
    latents: np.ndarray
    subframes: np.ndarray
    sim_times: np.ndarray

    @property
    def duration_us(self) -> int:
        """From the first exposure start to the last exposure end."""
        return int(self.exposure_end[-1] - self.exposure_start[0])

    def normalised_time(self, t_us: np.ndarray) -> np.ndarray:
        """Time in [0, 1] over the clip (first latent 0, last latent 1)."""
        return (np.asarray(t_us, dtype=np.float64) - self.exposure_start[0]) / self.duration_us


def _even_instants(start: np.ndarray, end: np.ndarray, count: int) -> np.ndarray:
    """[n, count] integer instants evenly spaced from start to end inclusive."""
    frac = np.linspace(0.0, 1.0, count)
    return np.rint(start[:, None] + frac[None, :] * (end - start)[:, None]).astype(np.int64)


def make_timeline(n_frames: int, frame_interval_us: int, exposure_us: int, k: int, n_subframes: int,
                  sim_steps_per_exposure: int) -> Timeline:
    """The clip's instants: exposure p spans [p * interval, p * interval + exposure].

    The simulator steps are about exposure / sim_steps_per_exposure apart everywhere (inside and
    between exposures); every latent and sub-frame instant is one of them.
    """
    checks = {"n_frames": (n_frames, 1), "frame_interval_us": (frame_interval_us, 1), "exposure_us": (exposure_us, 1),
              "k": (k, 2), "n_subframes": (n_subframes, 2), "sim_steps_per_exposure": (sim_steps_per_exposure, 1)}
    for name, (value, least) in checks.items():
        if value < least:
            raise ValueError(f"make_timeline: {name} must be >= {least}, got {value}")
    if exposure_us > frame_interval_us:
        raise ValueError(f"make_timeline: exposure_us ({exposure_us}) exceeds frame_interval_us ({frame_interval_us})")
    start = np.arange(n_frames, dtype=np.int64) * frame_interval_us
    end = start + exposure_us
    latents = _even_instants(start, end, k)
    subframes = _even_instants(start, end, n_subframes)
    keys = np.unique(np.concatenate([latents.ravel(), subframes.ravel()]))
    step = exposure_us / sim_steps_per_exposure
    pieces = [keys[:1]]
    for a, b in zip(keys[:-1], keys[1:]):
        n = int(np.ceil((b - a) / step))
        pieces.append(np.rint(a + (b - a) * np.arange(1, n + 1) / n).astype(np.int64))
    sim_times = np.unique(np.concatenate(pieces))
    return Timeline(start, end, latents, subframes, sim_times)

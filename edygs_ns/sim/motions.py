"""Motions of the scene presets' moving objects (edygs_ns.sim.presets), laid out over the clip.

Every motion maps seconds on the clip's clock to an ObjectState. Unlike the rigid preset's
ObjectMotion (edygs_ns.sim.trajectory, world units per second), these are laid out in normalised
clip time tau = t_s / duration_s (0 at the first exposure start, 1 at the last exposure end), so a
preset puts its objects at the same places at tau = 0, 0.5 and 1 whatever the clip's length.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Tuple

import numpy as np

from edygs_ns.sim.shapes import ObjectState
from edygs_ns.sim.trajectory import axis_angle_matrix


class Motion(Protocol):
    """Anything that poses a shape over time."""

    def state(self, t_s: float) -> ObjectState:
        """Pose at ``t_s`` seconds."""


def _tau(t_s: float, duration_s: float) -> float:
    return float(t_s) / max(float(duration_s), 1e-12)


def _cycle(amplitude: float, cycles: float, phase: float, tau: float) -> float:
    """amplitude * sin(2 pi cycles tau + phase)."""
    return amplitude * np.sin(2.0 * np.pi * cycles * tau + phase)


@dataclass(frozen=True)
class LinearMotion:
    """Constant velocity through an anchor point, turning at a constant rate.

    Attributes:
        anchor: [3] centre at tau_anchor, world units.
        tau_anchor: normalised clip time of the anchor.
        travel: [3] displacement over the whole clip (tau 0 -> 1), world units.
        base_rotation: [3, 3] object-to-world rotation at tau = 0.
        spin_axis: [3] unit world axis the object turns about.
        spin: radians turned over the whole clip.
        duration_s: clip length, seconds.
    """

    anchor: np.ndarray
    tau_anchor: float
    travel: np.ndarray
    base_rotation: np.ndarray
    spin_axis: np.ndarray
    spin: float
    duration_s: float

    def centre_at(self, tau: float) -> np.ndarray:
        """[3] centre at normalised clip time ``tau``."""
        return self.anchor + (tau - self.tau_anchor) * self.travel

    def state(self, t_s: float) -> ObjectState:
        """Pose at ``t_s`` seconds (rest size)."""
        tau = _tau(t_s, self.duration_s)
        return ObjectState(self.centre_at(tau), axis_angle_matrix(self.spin_axis, self.spin * tau) @ self.base_rotation)


@dataclass(frozen=True)
class SquashStretchMotion:
    """A LinearMotion whose shape squashes and stretches at constant volume while it rocks.

    The scale along local x is exp(stretch[0] sin(...)), along local y exp(stretch[1] sin(...)),
    along local z their inverse product, so the volume stays the rest volume.

    Attributes:
        path: where the centre goes, and the steady turning.
        stretch: (x, y) log-amplitudes of the two independent scale oscillations.
        cycles: (x, y) oscillations of each over the clip.
        phases: (x, y) phases, radians.
        wobble: amplitude of the rocking, radians.
        wobble_cycles: rocking oscillations over the clip.
        wobble_phase: phase of the rocking, radians.
        wobble_axis: [3] unit world axis of the rocking.
    """

    path: LinearMotion
    stretch: Tuple[float, float]
    cycles: Tuple[float, float]
    phases: Tuple[float, float]
    wobble: float
    wobble_cycles: float
    wobble_phase: float
    wobble_axis: np.ndarray

    def scale_at(self, tau: float) -> np.ndarray:
        """[3] per-axis scale at normalised clip time ``tau`` (product 1)."""
        sx, sy = (np.exp(_cycle(a, c, p, tau)) for a, c, p in zip(self.stretch, self.cycles, self.phases))
        return np.array([sx, sy, 1.0 / (sx * sy)])

    def state(self, t_s: float) -> ObjectState:
        """Pose and deformation at ``t_s`` seconds."""
        tau = _tau(t_s, self.path.duration_s)
        base = self.path.state(t_s)
        rock = axis_angle_matrix(self.wobble_axis, _cycle(self.wobble, self.wobble_cycles, self.wobble_phase, tau))
        return ObjectState(base.centre, rock @ base.rotation, self.scale_at(tau))


@dataclass(frozen=True)
class ArmMotion:
    """A two-segment arm swinging in a plane: the upper segment turns about a fixed shoulder, the
    lower one about the elbow at the upper segment's tip, each joint with its own angle over time.

    Joint angle i is rest_angles[i] + amplitudes[i] sin(2 pi cycles[i] tau + phases[i]); the
    upper angle is measured from plane_u towards plane_v, the lower one from the upper segment.

    Attributes:
        shoulder: [3] fixed shoulder point, world units.
        plane_u: [3] unit in-plane axis (angle 0).
        plane_v: [3] unit in-plane axis perpendicular to plane_u (angle pi / 2).
        lengths: (upper, lower) joint-to-joint lengths, world units.
        rest_angles: (shoulder, elbow) mean angles, radians.
        amplitudes: (shoulder, elbow) swing amplitudes, radians.
        cycles: (shoulder, elbow) swings over the clip.
        phases: (shoulder, elbow) phases, radians.
        duration_s: clip length, seconds.
    """

    shoulder: np.ndarray
    plane_u: np.ndarray
    plane_v: np.ndarray
    lengths: Tuple[float, float]
    rest_angles: Tuple[float, float]
    amplitudes: Tuple[float, float]
    cycles: Tuple[float, float]
    phases: Tuple[float, float]
    duration_s: float

    def joint_angles(self, t_s: float) -> Tuple[float, float]:
        """(shoulder angle, elbow angle relative to the upper segment), radians, at ``t_s``."""
        tau = _tau(t_s, self.duration_s)
        return tuple(r + _cycle(a, c, p, tau) for r, a, c, p in  # type: ignore[return-value]
                     zip(self.rest_angles, self.amplitudes, self.cycles, self.phases))

    def _frame(self, angle: float) -> np.ndarray:
        """[3, 3] rotation: local x along the segment, local y in the plane, local z its normal."""
        along = np.cos(angle) * self.plane_u + np.sin(angle) * self.plane_v
        across = -np.sin(angle) * self.plane_u + np.cos(angle) * self.plane_v
        return np.stack([along, across, np.cross(along, across)], axis=1)

    def segment_state(self, segment: int, t_s: float) -> ObjectState:
        """Pose of segment 0 (upper) or 1 (lower): centre halfway between its joints."""
        if segment not in (0, 1):
            raise ValueError(f"ArmMotion.segment_state: segment must be 0 or 1, got {segment}")
        shoulder_angle, elbow_angle = self.joint_angles(t_s)
        upper = self._frame(shoulder_angle)
        if segment == 0:
            return ObjectState(self.shoulder + 0.5 * self.lengths[0] * upper[:, 0], upper)
        lower = self._frame(shoulder_angle + elbow_angle)
        elbow = self.shoulder + self.lengths[0] * upper[:, 0]
        return ObjectState(elbow + 0.5 * self.lengths[1] * lower[:, 0], lower)


@dataclass(frozen=True)
class ArmSegmentMotion:
    """One segment of an ArmMotion, as a Motion of its own.

    Attributes:
        arm: the whole arm.
        segment: 0 (upper, about the shoulder) or 1 (lower, about the elbow).
    """

    arm: ArmMotion
    segment: int

    def state(self, t_s: float) -> ObjectState:
        """Pose of this segment at ``t_s`` seconds."""
        return self.arm.segment_state(self.segment, t_s)

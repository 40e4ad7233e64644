"""The deformation field F(γ(sg(μ)), γ(t)) -> (Δμ, Δq, Δs) of Deformable 3D Gaussians.

An MLP of ``depth`` ReLU layers of ``width`` units with the encoded input concatenated again
after layer ``skip_layer``, and three linear heads. The heads start at zero so the field is the
identity when training switches it on (tests enforce this).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple, Union

import torch
from jaxtyping import Float
from torch import Tensor, nn


@dataclass
class DeformationConfig:
    """Shape of the deformation MLP (defaults: the paper / Deformable 3DGS)."""

    depth: int = 8
    """hidden layers"""
    width: int = 256
    """units per hidden layer"""
    skip_layer: int = 4
    """the encoded input is concatenated again after this layer"""
    xyz_frequencies: int = 10
    """positional-encoding frequencies of the canonical position"""
    time_frequencies: int = 6
    """positional-encoding frequencies of the time"""
    colour: bool = False
    """also learn an RGB offset per Gaussian and time (added to its evaluated colour)"""


def positional_encoding(x: Float[Tensor, "N D"], frequencies: int) -> Float[Tensor, "N D*(1+2F)"]:
    """[x, sin(2^k x), cos(2^k x) for k < F] (NeRF's γ; the input is included)."""
    scales = 2.0 ** torch.arange(frequencies, device=x.device, dtype=x.dtype)
    angles = (x[..., None, :] * scales[:, None]).flatten(-2)
    return torch.cat([x, torch.sin(angles), torch.cos(angles)], dim=-1)


class DeformationField(nn.Module):
    """Maps canonical centres and a time in [0, 1] to offsets of centre, rotation and scale."""

    def __init__(self, config: DeformationConfig) -> None:
        super().__init__()
        self.config = config
        xyz_dims = 3 * (1 + 2 * config.xyz_frequencies)
        time_dims = 1 + 2 * config.time_frequencies
        in_dims = xyz_dims + time_dims
        layers = []
        for i in range(config.depth):
            if i == 0:
                fan_in = in_dims
            elif i == config.skip_layer + 1:
                fan_in = config.width + in_dims
            else:
                fan_in = config.width
            layers.append(nn.Linear(fan_in, config.width))
        self.layers = nn.ModuleList(layers)
        self.head_xyz = nn.Linear(config.width, 3)
        self.head_rot = nn.Linear(config.width, 4)
        self.head_scale = nn.Linear(config.width, 3)
        self.head_colour = nn.Linear(config.width, 3) if config.colour else None
        for head in (self.head_xyz, self.head_rot, self.head_scale, self.head_colour):
            if head is not None:
                nn.init.zeros_(head.weight)
                nn.init.zeros_(head.bias)

    def prepare_load(self, state_dict: dict, prefix: str) -> None:
        """Before ``load_state_dict``: a checkpoint from before the colour head gets the zero head
        (no colour offset), so it renders as it was trained."""
        if self.head_colour is not None:
            for name, value in self.head_colour.state_dict().items():
                state_dict.setdefault(f"{prefix}head_colour.{name}", torch.zeros_like(value))

    def forward(
        self, means: Float[Tensor, "N 3"], time: Union[float, Tensor]
    ) -> Tuple[Float[Tensor, "N 3"], Float[Tensor, "N 4"], Float[Tensor, "N 3"]]:
        """Offsets at ``time`` (normalised, a float or a one-element tensor kept on the device) for
        Gaussians centred at ``means`` (no gradient flows into means)."""
        d_xyz, d_rot, d_scale, _ = self.offsets(means, time)
        return d_xyz, d_rot, d_scale

    def offsets(
        self, means: Float[Tensor, "N 3"], time: Union[float, Tensor]
    ) -> Tuple[Float[Tensor, "N 3"], Float[Tensor, "N 4"], Float[Tensor, "N 3"], Optional[Float[Tensor, "N 3"]]]:
        """``forward``'s offsets and the RGB offset [N, 3] (None without ``config.colour``)."""
        means = means.detach()
        if isinstance(time, Tensor):
            t = time.detach().to(means.dtype).reshape(1, 1).expand(means.shape[0], 1)
        else:
            t = means.new_full((means.shape[0], 1), float(time))
        encoded = torch.cat(
            [positional_encoding(means, self.config.xyz_frequencies), positional_encoding(t, self.config.time_frequencies)],
            dim=-1,
        )
        h = encoded
        for i, layer in enumerate(self.layers):
            if i == self.config.skip_layer + 1:
                h = torch.cat([h, encoded], dim=-1)
            h = torch.relu(layer(h))
        colour = self.head_colour(h) if self.head_colour is not None else None
        return self.head_xyz(h), self.head_rot(h), self.head_scale(h), colour


def quat_from_rotvec(rotvec: Float[Tensor, "... 3"]) -> Float[Tensor, "... 4"]:
    """Unit quaternions (w, x, y, z) of axis-angle vectors (radians); differentiable at zero."""
    angle = (rotvec.square().sum(-1, keepdim=True) + 1e-24).sqrt()
    half = angle / 2
    return torch.cat([torch.cos(half), torch.sin(half) / angle * rotvec], dim=-1)


def quat_multiply(a: Float[Tensor, "... 4"], b: Float[Tensor, "... 4"]) -> Float[Tensor, "... 4"]:
    """Hamilton product a ⊗ b (w, x, y, z), broadcast over leading dimensions."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


class RigidMotion(nn.Module):
    """The tracked rigid motions of the moving objects (``rigid_track.py``), a base under the MLP.

    Up to ``bodies`` rigid bodies, one per moving object found at the dynamic switch
    (``motion_init.py``). A deformed Gaussian belongs to the body whose centre is nearest in units
    of that body's ``reach``; if it lies within the reach, at time t it moves by
    x -> R_b(t) (x - c_b) + c_b + τ_b(t) and turns by R_b(t); the MLP adds its residual on top.
    R_b(t) = exp(ω_b(t)), τ_b(t) = size_b · shift_b(t) are linear interpolations of one (ω, shift)
    per training latent at the sorted latent ``times``, held at the ends. ω (radians) and shift
    (object sizes) are parameters: the tracker sets them at the dynamic switch and the dynamic
    phase refines them with the photometric losses. A body that was never set has reach 0 and moves
    nothing. Everything travels with the checkpoint, so rendering reproduces it.
    """

    def __init__(self, count: int, bodies: int = 1) -> None:
        super().__init__()
        if bodies < 1:
            raise ValueError(f"RigidMotion: bodies must be >= 1, got {bodies}")
        self.rotvecs = nn.Parameter(torch.zeros(bodies, count, 3))
        self.shifts = nn.Parameter(torch.zeros(bodies, count, 3))
        self.register_buffer("centre", torch.zeros(bodies, 3))
        self.register_buffer("reach", torch.zeros(bodies))
        self.register_buffer("size", torch.ones(bodies))
        self.register_buffer("times", torch.zeros(count))
        # host copy of whether a body was set: the reach changes only in set() and when loading
        self._active: Optional[bool] = None

    @property
    def bodies(self) -> int:
        return int(self.reach.shape[0])

    @property
    def active(self) -> bool:
        """Whether some body moves (reach > 0). Read from the device once after set() or a load,
        then kept on the host, so a training step does not wait for it."""
        if self._active is None:
            self._active = self.times.numel() > 0 and bool((self.reach > 0).any())
        return self._active

    def _load_from_state_dict(self, *args, **kwargs) -> None:
        self._active = None
        super()._load_from_state_dict(*args, **kwargs)

    @property
    def translations(self) -> Tensor:
        """[bodies, count, 3] world units."""
        return self.shifts * self.size[:, None, None]

    @torch.no_grad()
    def set(self, centre: Tensor, reach: float, size: float, times: Tensor, rotvecs: Tensor, translations: Tensor,
            body: int = 0) -> None:
        """Store the track of ``body``: one rotation vector and translation per training latent (any
        order of ``times``; sorted here); ``size`` (world units) is the unit of the trained shifts."""
        if times.shape[0] != self.times.shape[0]:
            raise ValueError(f"RigidMotion.set: {times.shape[0]} track times for {self.times.shape[0]} training latents")
        if size <= 0 or reach <= 0:
            raise ValueError(f"RigidMotion.set: size and reach must be positive, got {size}, {reach}")
        if not 0 <= body < self.bodies:
            raise ValueError(f"RigidMotion.set: body {body} out of range (0..{self.bodies - 1})")
        order = torch.argsort(times)
        self._active = self.times.numel() > 0  # this body's reach is positive: known on the host
        self.centre[body] = centre
        self.reach[body] = float(reach)
        self.size[body] = float(size)
        self.times.copy_(times[order])
        self.rotvecs[body] = rotvecs[order]
        self.shifts[body] = translations[order] / size

    def prepare_load(self, state_dict: dict, prefix: str) -> None:
        """Before ``load_state_dict``: a checkpoint from before the rigid motion existed gets the
        empty (motionless) one; one from the single-body version becomes body 0."""
        current = self.state_dict()
        single = state_dict.get(prefix + "rotvecs")
        if single is not None and single.dim() == 2:
            for name, value in current.items():
                old = state_dict.get(prefix + name)
                if old is None or name == "times":
                    continue
                padded = value.clone()
                padded[0] = old
                state_dict[prefix + name] = padded
        for name, value in current.items():
            state_dict.setdefault(prefix + name, value)

    def at(self, time: Union[float, Tensor]) -> Tuple[Tensor, Tensor]:
        """Interpolated rotation vectors [bodies, 3] and translations [bodies, 3] at ``time`` (a float,
        or a one-element tensor; on the buffers' device, no host round trip)."""
        times = self.times
        if isinstance(time, Tensor):
            t = time.detach().to(device=times.device, dtype=times.dtype).reshape(1)
        else:
            t = torch.full((1,), float(time), dtype=times.dtype, device=times.device)
        t = torch.minimum(torch.maximum(t, times[:1]), times[-1:])  # [1], held at the ends
        hi = torch.searchsorted(times, t).clamp(min(1, len(times) - 1), len(times) - 1)  # [1]
        lo = (hi - 1).clamp_min(0)
        w = ((t - times[lo]) / (times[hi] - times[lo]).clamp_min(1e-12)).clamp(0.0, 1.0)
        translations = self.translations
        rotvec = torch.lerp(self.rotvecs[:, lo], self.rotvecs[:, hi], w[:, None])[:, 0]
        return rotvec, torch.lerp(translations[:, lo], translations[:, hi], w[:, None])[:, 0]

    def assign(self, means: Float[Tensor, "N 3"]) -> Tuple[Tensor, Tensor]:
        """Body index [N] of each canonical centre (nearest in units of reach) and whether it lies
        within that body's reach [N] bool."""
        distance = (means[:, None, :] - self.centre[None]).norm(dim=-1)
        scaled = torch.where(self.reach > 0, distance / self.reach.clamp_min(1e-12), torch.full_like(distance, float("inf")))
        nearest = scaled.argmin(dim=1)
        return nearest, scaled.gather(1, nearest[:, None])[:, 0] <= 1.0

    def forward(
        self, means: Float[Tensor, "N 3"], quats: Float[Tensor, "N 4"], time: Union[float, Tensor]
    ) -> Tuple[Float[Tensor, "N 3"], Float[Tensor, "N 4"]]:
        """Offsets (Δμ, Δq) of the rigid motions at ``time`` (zero outside every reach or when empty)."""
        if not self.active:
            return torch.zeros_like(means), torch.zeros_like(quats)
        rotvec, translation = self.at(time)
        means = means.detach()
        body, inside = self.assign(means)
        quat = quat_from_rotvec(rotvec)  # [B, 4]
        rotation = quat_to_matrix(quat)[body]  # [N, 3, 3]
        centre = self.centre[body]
        moved = torch.einsum("nij,nj->ni", rotation, means - centre) + centre + translation[body]
        turned = quat_multiply(quat[body], quats)
        weight = inside[:, None].to(means.dtype)
        return weight * (moved - means), weight * (turned - quats)


def quat_to_matrix(q: Float[Tensor, "... 4"]) -> Float[Tensor, "... 3 3"]:
    """Rotation matrices of unit quaternions (w, x, y, z)."""
    w, x, y, z = q.unbind(-1)
    rows = [
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], dim=-1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], dim=-1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=-1),
    ]
    return torch.stack(rows, dim=-2)

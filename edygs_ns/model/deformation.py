"""The deformation field F(γ(sg(μ)), γ(t)) -> (Δμ, Δq, Δs) of Deformable 3D Gaussians.

An MLP of ``depth`` ReLU layers of ``width`` units with the encoded input concatenated again
after layer ``skip_layer``, and three linear heads. The heads start at zero so the field is the
identity when training switches it on (tests enforce this).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

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
    """positional-encoding frequencies of the canonical position (3 + 3·2·10 = 63 dims)"""
    time_frequencies: int = 6
    """positional-encoding frequencies of the time"""


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
        for head in (self.head_xyz, self.head_rot, self.head_scale):
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)

    def forward(
        self, means: Float[Tensor, "N 3"], time: float
    ) -> Tuple[Float[Tensor, "N 3"], Float[Tensor, "N 4"], Float[Tensor, "N 3"]]:
        """Offsets at ``time`` for Gaussians centred at ``means`` (no gradient flows into means)."""
        means = means.detach()
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
        return self.head_xyz(h), self.head_rot(h), self.head_scale(h)

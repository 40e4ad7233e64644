"""How many training views see the static surface behind a pixel (model/view_support.py)."""

from __future__ import annotations

import torch

from edygs_ns.model.view_support import relative_support, typical_support, view_support

H, W, F, N = 40, 60, 50.0, 11
WALL = 4.0  # a wall facing the cameras, this far in front of them (world units)


def _sliding(step: float):
    """N cameras looking down +z at the wall, each ``step`` further along +x (OpenCV axes)."""
    c2w = torch.eye(4).repeat(N, 1, 1)
    c2w[:, 0, 3] = torch.arange(N, dtype=torch.float32) * step
    viewmats = torch.linalg.inv(c2w)
    Ks = torch.tensor([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]]).repeat(N, 1, 1)
    return torch.full((N, H, W), WALL), viewmats, c2w, Ks


def _column(k: int, col: int) -> torch.Tensor:
    pixels = torch.zeros(N, H, W, dtype=torch.bool)
    pixels[k, :, col] = True
    return pixels


def test_a_still_camera_sees_every_pixel_from_every_view():
    depth, viewmats, c2w, Ks = _sliding(0.0)
    assert torch.allclose(view_support(torch.ones(N, H, W, dtype=torch.bool), depth, viewmats, c2w, Ks), torch.tensor(1.0))
    assert typical_support(depth, viewmats, c2w, Ks) == 1.0


def test_the_edge_the_camera_moves_away_from_is_seen_by_few_views():
    # the cameras move right by 1/20 of the wall's width in view per step: the first view's left
    # edge leaves the frame after a few steps, its centre stays in view throughout
    depth, viewmats, c2w, Ks = _sliding(WALL * W / F / 20)
    left = float(view_support(_column(0, 1), depth, viewmats, c2w, Ks).median())
    centre = float(view_support(_column(0, W // 2), depth, viewmats, c2w, Ks).median())
    right_of_last = float(view_support(_column(N - 1, W - 2), depth, viewmats, c2w, Ks).median())
    assert centre == 1.0
    assert left < 0.3 and right_of_last < 0.3
    # against the clip's typical pixel: the left edge of the first view is a small share of it
    typical = typical_support(depth, viewmats, c2w, Ks)
    assert 0.6 < typical <= 1.0
    assert relative_support(_column(0, 1), typical, depth, viewmats, c2w, Ks) < 0.4
    assert relative_support(_column(N // 2, W // 2), typical, depth, viewmats, c2w, Ks) >= 1.0


def test_pixels_without_a_static_surface_are_not_scored():
    depth, viewmats, c2w, Ks = _sliding(0.5)
    depth[:, :, : W // 2] = 0.0  # nothing rendered on the left half
    assert len(view_support(_column(0, 1), depth, viewmats, c2w, Ks)) == 0
    assert relative_support(_column(0, 1), 0.8, depth, viewmats, c2w, Ks) == 1.0  # no say either way
    assert len(view_support(_column(0, W - 2), depth, viewmats, c2w, Ks)) == H

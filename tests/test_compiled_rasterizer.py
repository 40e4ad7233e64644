"""The compiled CPU rasteriser against the torch reference: images, radii and every gradient."""

from __future__ import annotations

import math
from typing import Dict, Optional, Tuple

import pytest
import torch
from torch import Tensor

import edygs_ns.render.cpu_backend as cpu_backend
from edygs_ns.render.contract import select_backend
from edygs_ns.render.cpu_backend import compiled_available, rasterize_cpu
from edygs_ns.render.torch_backend import TILE_SIZE, rasterize_torch

pytestmark = [
    pytest.mark.usefixtures("one_thread"),
    pytest.mark.skipif(not compiled_available(), reason="the compiled CPU rasteriser cannot be built here (no g++/ninja?)"),
]

PARAMS = ("means", "quats", "scales", "opacities", "features", "viewmats")
#: relative tolerance (of each tensor's largest entry) per dtype: float64 differs only in rounding
#: and summation order; float32 also in exp and in 1 / (1 - alpha) amplified near ALPHA_MAX.
TOLERANCE = {torch.float64: 1e-9, torch.float32: 2e-3}


def make_scene(n: int, width: int, height: int, n_cams: int = 1, channels: int = 4, seed: int = 0,
               per_camera: bool = False) -> Dict[str, Tensor]:
    """n Gaussians in front of n_cams pinhole cameras near the origin looking along +z (float64)."""
    g = torch.Generator().manual_seed(seed)
    dt = torch.float64
    focal = 0.9 * width
    z = 2.0 + 3.0 * torch.rand(n, generator=g, dtype=dt)
    half = torch.tensor([0.6 * width / focal, 0.6 * height / focal], dtype=dt)
    xy = (torch.rand(n, 2, generator=g, dtype=dt) * 2 - 1) * half * z[:, None]
    sigma_px = 0.5 + 2.5 * torch.rand(n, 1, generator=g, dtype=dt)
    scales = sigma_px * z[:, None] / focal * torch.exp(0.4 * torch.randn(n, 3, generator=g, dtype=dt))
    viewmats = torch.eye(4, dtype=dt).repeat(n_cams, 1, 1)
    for c in range(1, n_cams):  # small turns and shifts
        angle = 0.05 * c
        viewmats[c, 0, 0] = viewmats[c, 2, 2] = math.cos(angle)
        viewmats[c, 0, 2], viewmats[c, 2, 0] = math.sin(angle), -math.sin(angle)
        viewmats[c, :3, 3] = torch.tensor([0.1 * c, -0.05 * c, 0.2 * c], dtype=dt)
    ks = torch.tensor([[focal, 0.0, width / 2 + 0.3], [0.0, focal, height / 2 - 0.2], [0.0, 0.0, 1.0]], dtype=dt)
    feat_shape = (n_cams, n, channels) if per_camera else (n, channels)
    return {
        "means": torch.cat([xy, z[:, None]], 1),
        "quats": torch.randn(n, 4, generator=g, dtype=dt),
        "scales": scales,
        "opacities": 0.05 + 0.9 * torch.rand(n, generator=g, dtype=dt),
        "features": torch.rand(feat_shape, generator=g, dtype=dt),
        "viewmats": viewmats,
        "Ks": ks.repeat(n_cams, 1, 1),
    }


def render_with_grads(backend, scene: Dict[str, Tensor], width: int, height: int, dtype: torch.dtype,
                      backgrounds: Optional[Tensor] = None, **kwargs) -> Tuple[object, Dict[str, Tensor]]:
    """Render, back-propagate a random linear loss of render, depth and alpha; return outputs and grads."""
    leaves = {k: v.detach().to(dtype).clone().requires_grad_(k in PARAMS) for k, v in scene.items()}
    bg = backgrounds.to(dtype) if backgrounds is not None else None
    out = backend(
        leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["features"],
        leaves["viewmats"], leaves["Ks"], width, height, backgrounds=bg, **kwargs,
    )
    g = torch.Generator().manual_seed(7)
    w_render = torch.randn(out.render.shape, generator=g, dtype=torch.float64).to(dtype)
    w_alpha = torch.randn(out.alpha.shape, generator=g, dtype=torch.float64).to(dtype)
    # expected depth is ill-conditioned where alpha is tiny: weight it by alpha (as training does)
    loss = (out.render * w_render).sum() + (out.alpha * w_alpha).sum() + (out.depth * out.alpha.detach()).sum()
    loss.backward()
    grads = {k: leaves[k].grad for k in PARAMS}
    grads["means2d"] = out.means2d.grad
    return out, grads


def assert_same(scene: Dict[str, Tensor], width: int, height: int, dtype: torch.dtype = torch.float64,
                backgrounds: Optional[Tensor] = None, **kwargs) -> object:
    """Forward outputs, radii and every gradient of both backends agree; returns the reference output."""
    ref, ref_grads = render_with_grads(rasterize_torch, scene, width, height, dtype, backgrounds, **kwargs)
    out, grads = render_with_grads(rasterize_cpu, scene, width, height, dtype, backgrounds, **kwargs)
    rel = TOLERANCE[dtype]

    def close(a: Tensor, b: Tensor, name: str) -> None:
        atol = rel * float(b.detach().abs().max()) if b.numel() else 0.0
        torch.testing.assert_close(a, b, rtol=rel, atol=max(atol, 1e-30), msg=lambda m: f"{name}: {m}")

    assert torch.equal(out.radii, ref.radii) and torch.equal(out.visible, ref.visible)
    for name in ("render", "depth", "alpha"):
        close(getattr(out, name), getattr(ref, name), name)
    for name, ref_grad in ref_grads.items():
        assert grads[name] is not None and ref_grad is not None, name
        close(grads[name], ref_grad, f"grad of {name}")
    return ref


@pytest.mark.parametrize("n,width,height", [(40, 21, 14), (300, 64, 48), (2000, 100, 75)])
def test_random_scenes_match(n: int, width: int, height: int) -> None:
    ref = assert_same(make_scene(n, width, height, seed=n), width, height)
    assert ref.visible.any() and float(ref.alpha.max()) > 0.5


def test_float32_matches() -> None:
    assert_same(make_scene(500, 64, 40, seed=3), 64, 40, dtype=torch.float32)


@pytest.mark.parametrize("channels,per_camera", [(3, False), (4, True), (2, False), (6, True)])
def test_cameras_and_feature_layouts(channels: int, per_camera: bool) -> None:
    """C = 3 cameras; [N, D] and [C, N, D] features; D = 3, 4 (fused loops) and 2, 6 (generic)."""
    scene = make_scene(200, 40, 30, n_cams=3, channels=channels, seed=channels, per_camera=per_camera)
    backgrounds = torch.rand(3, channels, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    assert_same(scene, 40, 30, backgrounds=backgrounds)


def test_tile_edges() -> None:
    """Centres on tile corners and edges, on the image border and just outside it; W, H not tile multiples."""
    width, height = 3 * TILE_SIZE + 3, 2 * TILE_SIZE + 5
    scene = make_scene(36, width, height, seed=4)
    focal, cx, cy = (float(scene["Ks"][0, i, j]) for i, j in ((0, 0), (0, 2), (1, 2)))
    grid = [(x, y) for x in (0.0, TILE_SIZE, 2 * TILE_SIZE, width - 0.5, width + 1.5, -1.0)
            for y in (0.0, TILE_SIZE, height - 0.01, height + 2.0, -1.5, 2 * TILE_SIZE)]
    z = scene["means"][:, 2]
    scene["means"][:, 0] = (torch.tensor([x for x, _ in grid], dtype=torch.float64) - cx) / focal * z
    scene["means"][:, 1] = (torch.tensor([y for _, y in grid], dtype=torch.float64) - cy) / focal * z
    ref = assert_same(scene, width, height)
    assert ref.visible.sum() >= 20


def test_tall_thin_gaussians() -> None:
    """Needles: one long axis, two thin ones, turned around the view axis."""
    scene = make_scene(60, 48, 40, seed=5)
    scene["scales"][:, 0] = 0.003
    scene["scales"][:, 1] = 0.6
    scene["scales"][:, 2] = 0.003
    angle = torch.linspace(0.0, math.pi, 60, dtype=torch.float64)
    scene["quats"] = torch.stack([torch.cos(angle / 2), 0 * angle, 0 * angle, torch.sin(angle / 2)], 1)
    assert_same(scene, 48, 40)


def test_empty_tiles_and_opaque_pile() -> None:
    """All Gaussians in one corner (most tiles empty), many nearly opaque: the alpha clamp and the
    transmittance stop both happen."""
    scene = make_scene(150, 64, 48, seed=6)
    scene["means"][:, :2] = scene["means"][:, :2] * 0.15 - 0.35 * scene["means"][:, 2:3]
    scene["opacities"][:100] = 0.9995
    ref = assert_same(scene, 64, 48)
    assert float(ref.alpha[0, -8:, -8:].max()) == 0.0 and float(ref.alpha.max()) > 0.999


def test_near_far_culling() -> None:
    scene = make_scene(300, 40, 30, seed=8)
    ref = assert_same(scene, 40, 30, near_plane=2.8, far_plane=4.2)
    z = scene["means"][:, 2]
    assert not ref.visible[0, (z < 2.7) | (z > 4.3)].any() and ref.visible.any()


def test_nothing_visible_renders_the_background() -> None:
    scene = make_scene(20, 24, 16, seed=9)
    scene["means"][:, 2] = -3.0  # behind the camera
    background = torch.tensor([[0.2, 0.4, 0.6, 0.0]], dtype=torch.float64)
    out, grads = render_with_grads(rasterize_cpu, scene, 24, 16, torch.float64, background)
    assert not out.visible.any() and torch.all(out.alpha == 0)
    torch.testing.assert_close(out.render, background[:, None, None, :].expand_as(out.render))
    assert all(torch.all(grads[k] == 0) for k in ("means", "opacities", "features"))


def test_no_grad_forward_matches() -> None:
    scene = make_scene(200, 32, 24, seed=10)
    args = [scene[k] for k in ("means", "quats", "scales", "opacities", "features", "viewmats", "Ks")]
    with torch.no_grad():
        out, ref = rasterize_cpu(*args, 32, 24), rasterize_torch(*args, 32, 24)
    torch.testing.assert_close(out.render, ref.render, rtol=1e-9, atol=1e-12)


def test_select_backend_prefers_the_compiled_one_on_cpu() -> None:
    assert select_backend(torch.device("cpu")) is rasterize_cpu
    assert select_backend(torch.device("cpu"), "cpu") is rasterize_cpu
    assert select_backend(torch.device("cpu"), "torch") is rasterize_torch
    with pytest.raises(ValueError, match="CPU tensors"):
        select_backend(torch.device("meta"), "cpu")


def test_falls_back_to_torch_when_it_cannot_build(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(cpu_backend, "load_extension", lambda: None)
    assert select_backend(torch.device("cpu")) is rasterize_torch
    with pytest.raises(RuntimeError, match="rasterizer torch"):
        select_backend(torch.device("cpu"), "cpu")


def test_two_threads_match_and_repeat() -> None:
    """OpenMP over tiles and Gaussians (per-thread gradient sums): parity holds, and two runs with the
    same thread count give the same bits."""
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        scene = make_scene(400, 56, 40, n_cams=2, seed=11)
        assert_same(scene, 56, 40)
        runs = [render_with_grads(rasterize_cpu, scene, 56, 40, torch.float32)[1] for _ in range(2)]
        assert all(torch.equal(runs[0][k], runs[1][k]) for k in runs[0])
    finally:
        torch.set_num_threads(threads)


def test_intrinsics_gradient_uses_the_torch_projection() -> None:
    """The compiled projection has no Ks gradient: with Ks requiring one, the torch projection runs
    under autograd and Ks.grad matches the reference."""
    scene = make_scene(150, 40, 30, seed=12)
    grads = []
    for backend in (rasterize_torch, rasterize_cpu):
        ks = scene["Ks"].clone().requires_grad_(True)
        args = [scene[k].clone().requires_grad_(k in PARAMS) for k in ("means", "quats", "scales", "opacities",
                                                                        "features", "viewmats")]
        out = backend(*args, ks, 40, 30)
        (out.render.sum() + out.alpha.sum()).backward()
        grads.append(ks.grad)
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-9, atol=1e-9 * float(grads[0].abs().max()))


def test_build_name_separates_checkouts(tmp_path, monkeypatch) -> None:
    """Two checkouts of the same source get two cached builds (torch rebuilds a module whose source
    path changed, so a shared name made them rebuild over each other); the same checkout keeps its name."""
    import shutil

    import edygs_ns.render.compiled as compiled

    here = compiled.module_name()
    assert compiled.module_name() == here
    copy = tmp_path / "csrc" / compiled.SOURCE.name
    copy.parent.mkdir()
    shutil.copy(compiled.SOURCE, copy)
    monkeypatch.setattr(compiled, "SOURCE", copy)
    assert compiled.module_name() != here

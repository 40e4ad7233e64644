"""Parity of the two backends on CUDA: the torch reference against gsplat 1.4.0 (skipped without CUDA)."""

from __future__ import annotations

from typing import Dict

import pytest
import torch
from torch import Tensor

from edygs_ns.render.contract import select_backend
from edygs_ns.render.torch_backend import rasterize_torch

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")

WIDTH, HEIGHT = 61, 47
PARAM_NAMES = ("means", "quats", "scales", "opacities", "features", "viewmats")
#: both backends bin with the same tile edge, so the same far tails are cut
TILE = 16


def make_scene(n: int, seed: int) -> Dict[str, Tensor]:
    """n Gaussians in front of two cameras (OpenCV), 4 feature channels (RGB + mask)."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([2.0, 1.5, 1.0]) + torch.tensor([0.0, 0.0, 4.0])
    viewmats = torch.eye(4).repeat(2, 1, 1)
    viewmats[1, :3, :3] = torch.tensor([[0.995, 0.0, 0.0998], [0.0, 1.0, 0.0], [-0.0998, 0.0, 0.995]])
    viewmats[1, 0, 3] = -0.2
    ks = torch.tensor([[50.0, 0.0, WIDTH / 2], [0.0, 50.0, HEIGHT / 2], [0.0, 0.0, 1.0]]).repeat(2, 1, 1)
    return {
        "means": means,
        "quats": torch.randn(n, 4, generator=g),
        "scales": 0.02 + 0.1 * torch.rand(n, 3, generator=g),
        "opacities": 0.1 + 0.85 * torch.rand(n, generator=g),
        "features": torch.rand(n, 4, generator=g),
        "viewmats": viewmats,
        "Ks": ks,
        "backgrounds": torch.tensor([[0.3, 0.2, 0.1, 0.0], [1.0, 1.0, 1.0, 0.0]]),
    }


def render_and_grad(backend, scene: Dict[str, Tensor], device: str):
    leaves = {k: v.to(device).clone().requires_grad_(k in PARAM_NAMES) for k, v in scene.items()}
    out = backend(
        leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["features"],
        leaves["viewmats"], leaves["Ks"], WIDTH, HEIGHT, backgrounds=leaves["backgrounds"], tile_size=TILE,
    )
    g = torch.Generator().manual_seed(1)
    w_render = torch.randn(out.render.shape, generator=g).to(device)
    w_depth = torch.randn(out.depth.shape, generator=g).to(device)
    ((out.render * w_render).sum() + (out.depth * w_depth * out.alpha.detach()).sum() + out.alpha.sum()).backward()
    grads = {k: leaves[k].grad.detach().cpu() for k in PARAM_NAMES}
    return out, grads


def relative_error(a: Tensor, b: Tensor) -> float:
    return float((a - b).norm() / b.norm().clamp(min=1e-12))


def test_select_backend_picks_gsplat_on_cuda() -> None:
    from edygs_ns.render.gsplat_backend import rasterize_gsplat

    assert select_backend(torch.device("cuda")) is rasterize_gsplat
    assert select_backend(torch.device("cuda"), "torch") is rasterize_torch


@pytest.mark.parametrize("seed", [0, 1])
def test_torch_backend_matches_gsplat(seed: int) -> None:
    from edygs_ns.render.gsplat_backend import rasterize_gsplat

    scene = make_scene(300, seed)
    ours, ours_grads = render_and_grad(rasterize_torch, scene, "cpu")
    theirs, their_grads = render_and_grad(rasterize_gsplat, scene, "cuda")
    assert torch.equal(ours.radii.cpu(), theirs.radii.cpu().to(ours.radii.dtype))
    vis = ours.visible.cpu()
    assert vis.sum() > 100
    torch.testing.assert_close(ours.means2d.detach()[vis], theirs.means2d.detach().cpu()[vis], atol=1e-3, rtol=1e-5)
    # gsplat evaluates exp with fast math (__expf): images agree to a few 1e-5
    torch.testing.assert_close(ours.render.detach(), theirs.render.detach().cpu(), atol=2e-4, rtol=0)
    torch.testing.assert_close(ours.alpha.detach(), theirs.alpha.detach().cpu(), atol=2e-4, rtol=0)
    covered = ours.alpha.detach() > 0.2
    torch.testing.assert_close(ours.depth.detach()[covered], theirs.depth.detach().cpu()[covered], atol=1e-3, rtol=1e-3)
    for name in PARAM_NAMES:
        err = relative_error(ours_grads[name], their_grads[name])
        assert err < 1e-2, f"{name}: gradients differ by {err:.2e} (relative)"
    err = relative_error(ours.means2d.grad[vis], theirs.means2d.grad.cpu()[vis])
    assert err < 1e-2, f"means2d.grad differs by {err:.2e} (relative)"


def test_torch_backend_runs_on_cuda_tensors() -> None:
    scene = make_scene(200, 2)
    on_cpu, cpu_grads = render_and_grad(rasterize_torch, scene, "cpu")
    on_gpu, gpu_grads = render_and_grad(rasterize_torch, scene, "cuda")
    torch.testing.assert_close(on_gpu.render.detach().cpu(), on_cpu.render.detach(), atol=1e-5, rtol=0)
    for name in PARAM_NAMES:
        assert relative_error(gpu_grads[name], cpu_grads[name]) < 1e-4, name


def test_gsplat_renders_gaussians_per_camera_as_single_calls() -> None:
    # a training pair: the second camera's Gaussians moved (a later time), one call for both
    scene = {k: v.cuda() for k, v in make_scene(400, seed=2).items()}
    g = torch.Generator().manual_seed(3)
    shift = (0.05 * torch.randn(400, 3, generator=g)).cuda()
    per_camera = {
        "means": torch.stack([scene["means"], scene["means"] + shift]).requires_grad_(True),
        "quats": torch.stack([scene["quats"], scene["quats"]]).requires_grad_(True),
        "scales": torch.stack([scene["scales"], scene["scales"] * 1.1]).requires_grad_(True),
    }
    gsplat = select_backend(torch.device("cuda"))
    both = gsplat(per_camera["means"], per_camera["quats"], per_camera["scales"], scene["opacities"], scene["features"],
                  scene["viewmats"], scene["Ks"], WIDTH, HEIGHT, backgrounds=scene["backgrounds"])
    singles = [
        gsplat(per_camera["means"][c], per_camera["quats"][c], per_camera["scales"][c], scene["opacities"],
               scene["features"], scene["viewmats"][c : c + 1], scene["Ks"][c : c + 1], WIDTH, HEIGHT,
               backgrounds=scene["backgrounds"][c : c + 1])
        for c in range(2)
    ]
    for name in ("render", "depth", "alpha", "radii", "means2d"):
        torch.testing.assert_close(getattr(both, name), torch.cat([getattr(s, name) for s in singles]), rtol=1e-5, atol=1e-5)
    weights = torch.rand(both.render.shape, generator=g).cuda()
    grads_both = torch.autograd.grad((both.render * weights).sum(), list(per_camera.values()))
    loss = sum((s.render * weights[c : c + 1]).sum() for c, s in enumerate(singles))
    grads_single = torch.autograd.grad(loss, list(per_camera.values()))
    for a, b in zip(grads_both, grads_single):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)
    torch_pair = rasterize_torch(per_camera["means"], per_camera["quats"], per_camera["scales"], scene["opacities"],
                                 scene["features"], scene["viewmats"], scene["Ks"], WIDTH, HEIGHT,
                                 backgrounds=scene["backgrounds"], tile_size=TILE)
    # gsplat evaluates exp with fast math (__expf): images agree to a few 1e-5
    torch.testing.assert_close(torch_pair.render.detach(), both.render.detach(), atol=2e-4, rtol=0)

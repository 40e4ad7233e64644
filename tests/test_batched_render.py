"""The training pair in one rasteriser call, and the device-side replacements of host round trips
(issue 19 item 3): each must give what the code it replaced gave."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path
from typing import Dict

import pytest
import torch
from torch import Tensor
from torch.testing import assert_close

sys.path.insert(0, str(Path(__file__).parent))
from test_rasterizer import HEIGHT, WIDTH, make_scene  # noqa: E402
from train_helpers import make_tiny_scene, tiny_trainer_config  # noqa: E402

from edygs_ns.losses.blur import blur_loss  # noqa: E402
from edygs_ns.model.exposure_cache import NO_EXPOSURE, ExposureCache  # noqa: E402
from edygs_ns.model.strategy import DensifyConfig, make_strategy  # noqa: E402
from edygs_ns.render.contract import RasterOutputs, select_backend  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
OUTPUTS = ("render", "depth", "alpha", "radii")


def _pair_scene(device: str = "cpu") -> Dict[str, Tensor]:
    """Two cameras; the Gaussians of the second moved and turned a little (a later time)."""
    scene = {k: v.float().to(device) for k, v in make_scene(60, 2, seed=3).items()}
    g = torch.Generator().manual_seed(5)
    shift = (0.05 * torch.randn(60, 3, generator=g)).to(device)
    scene["means"] = torch.stack([scene["means"], scene["means"] + shift])
    scene["quats"] = torch.stack([scene["quats"], scene["quats"] + 0.1 * shift.abs().sum(-1, keepdim=True)])
    scene["scales"] = torch.stack([scene["scales"], scene["scales"] * 1.1])
    scene["features"] = torch.stack([scene["features"], scene["features"].flip(-1)])
    return scene


def _render(backend, scene: Dict[str, Tensor], cams: slice) -> RasterOutputs:
    per_camera = cams.stop - cams.start > 1
    geometry = [scene[k][cams] if per_camera else scene[k][cams.start] for k in ("means", "quats", "scales")]
    features = scene["features"][cams] if per_camera else scene["features"][cams.start]
    return backend(*geometry, scene["opacities"], features, scene["viewmats"][cams], scene["Ks"][cams], WIDTH, HEIGHT,
                   backgrounds=torch.full((cams.stop - cams.start, 4), 0.2, device=scene["means"].device))


def _grads(scene: Dict[str, Tensor], out: RasterOutputs, weights: Tensor) -> Dict[str, Tensor]:
    loss = (out.render * weights).sum() + out.depth.sum() * 1e-2 + out.alpha.sum()
    names = ("means", "quats", "scales", "opacities", "features")
    return dict(zip(names, torch.autograd.grad(loss, [scene[k] for k in names])))


def _check_pair_parity(backend_name: str, device: str) -> None:
    backend = select_backend(torch.device(device), backend_name)
    scene = _pair_scene(device)
    for k in ("means", "quats", "scales", "opacities", "features"):
        scene[k].requires_grad_(True)
    weights = torch.rand(2, HEIGHT, WIDTH, 4, generator=torch.Generator().manual_seed(1)).to(device)
    both = _render(backend, scene, slice(0, 2))
    grads_both = _grads(scene, both, weights)
    singles = [_render(backend, scene, slice(c, c + 1)) for c in range(2)]
    for name in OUTPUTS:
        assert_close(getattr(both, name), torch.cat([getattr(s, name) for s in singles]), rtol=1e-5, atol=1e-5)
    assert_close(both.means2d, torch.cat([s.means2d for s in singles]), rtol=1e-6, atol=1e-5)
    loss = sum((s.render * weights[c : c + 1]).sum() + s.depth.sum() * 1e-2 + s.alpha.sum() for c, s in enumerate(singles))
    names = ("means", "quats", "scales", "opacities", "features")
    grads_single = dict(zip(names, torch.autograd.grad(loss, [scene[k] for k in names], retain_graph=True)))
    for name in names:
        assert_close(grads_both[name], grads_single[name], rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("backend_name", ["torch", "cpu"])
def test_a_pair_in_one_call_equals_two_calls(backend_name: str) -> None:
    # gsplat's: tests/test_rasterizer_parity_cuda.py (run by scripts/gpu_check.sh)
    _check_pair_parity(backend_name, "cpu")


def test_the_densification_gradient_of_a_pair_is_its_first_camera() -> None:
    backend = select_backend(torch.device("cpu"), "cpu")
    scene = _pair_scene()
    for k in ("means", "quats", "scales"):
        scene[k].requires_grad_(True)
    both = _render(backend, scene, slice(0, 2))
    first = _render(backend, scene, slice(0, 1))
    weights = torch.rand(2, HEIGHT, WIDTH, 4, generator=torch.Generator().manual_seed(2))
    ((both.render * weights).sum()).backward()
    ((first.render * weights[:1]).sum()).backward()
    assert_close(both.means2d.grad[:1], first.means2d.grad, rtol=1e-5, atol=1e-7)


def test_the_strategy_statistics_match_gsplats_without_a_host_read() -> None:
    from gsplat.strategy import DefaultStrategy

    n = 50
    g = torch.Generator().manual_seed(0)
    means2d = torch.randn(2, n, 2, generator=g)
    means2d.grad = torch.randn(2, n, 2, generator=g)
    radii = (torch.rand(2, n, generator=g) > 0.4).int() * 3
    params = {"means": torch.zeros(n, 3)}
    ours, theirs = make_strategy(DensifyConfig()), DefaultStrategy()
    for counted in (1, 2):
        info = {"means2d": means2d, "radii": radii, "width": 40, "height": 30, "n_cameras": counted, "gaussian_ids": None}
        state_ours, state_theirs = {"grad2d": None, "count": None}, {"grad2d": None, "count": None}
        ours._update_state(params, state_ours, dict(info, n_cameras=2, counted_cameras=counted))
        sliced = dict(info, means2d=means2d[:counted], radii=radii[:counted])
        sliced["means2d"] = means2d[:counted].detach().requires_grad_(True)
        sliced["means2d"].grad = means2d.grad[:counted]
        DefaultStrategy._update_state(theirs, params, state_theirs, sliced)
        assert_close(state_ours["grad2d"], state_theirs["grad2d"])
        assert torch.equal(state_ours["count"], state_theirs["count"])


def test_the_exposure_completed_on_the_device_gives_the_same_blur_loss() -> None:
    # exposures 0 and 1 of 3 and 2 training latents (a held-out view), a novel view without one
    cache = ExposureCache(torch.tensor([0, 0, 0, 1, 1, NO_EXPOSURE]))
    g = torch.Generator().manual_seed(0)
    frames = torch.rand(6, 4, 5, 3, generator=g)
    cache.fill(lambda i: frames[i])
    target = torch.rand(1, 4, 5, 3, generator=g)
    for batch in ([0, 1], [2], [3, 4], [4]):
        indices = torch.tensor(batch)
        live = torch.rand(len(batch), 4, 5, 3, generator=g)
        (expected,) = cache.complete(indices, live).values()
        stack, weights = cache.complete_on_device(indices, live)
        assert_close(blur_loss(stack, target, weights), blur_loss(expected[None], target))
        k = len(expected)
        assert_close(stack[0, :k], expected) and torch.equal(weights[0, :k], torch.ones(k))
        assert not weights[0, k:].any()


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny EDyGS trainer in the dynamic phase, with a non-zero deformation, mixed motion-mask
    values and one rigid body (no training: the renders are compared, not their quality)."""
    torch.manual_seed(0)
    root = tmp_path_factory.mktemp("batched")
    scene = make_tiny_scene(root, room_init=True)
    config = tiny_trainer_config(scene, root / "runs", iters=20, pose_init=2, static=6)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    model = trainer.pipeline.model
    model.train()
    model.step = 10
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for head in (model.deformation.head_xyz, model.deformation.head_rot, model.deformation.head_scale):
            head.weight.copy_(0.02 * torch.randn(head.weight.shape, generator=g))
        mask = model.gauss_params["mask_logit"]
        mask.copy_(2.0 * torch.randn(mask.shape, generator=g))
    n = model.rigid_motion.times.shape[0]
    times = trainer.pipeline.datamanager.train_cameras.times.reshape(-1)
    model.rigid_motion.set(torch.zeros(3), 10.0, 1.0, times, 0.05 * torch.randn(n, 3, generator=g), 0.05 * torch.randn(n, 3, generator=g))
    return trainer


def _forward(trainer, camera, batch) -> Dict[str, Tensor]:
    model = trainer.pipeline.model
    outputs = model.get_outputs(camera)
    losses = model.get_loss_dict(outputs, batch)
    total = sum(losses.values())
    params = list(model.deformation.parameters()) + [model.gauss_params["means"], model.gauss_params["mask_logit"]]
    grads = torch.autograd.grad(total, params, allow_unused=True)
    result = {k: outputs[k].detach() for k in ("rgb", "mask", "depth", "accumulation")}
    result.update({f"loss {k}": v.detach() for k, v in losses.items()})
    result.update({f"grad {i}": g for i, g in enumerate(grads) if g is not None})
    return result


def test_the_masked_deformation_equals_the_gathered_subset(trained) -> None:
    model = trained.pipeline.model
    camera, batch = trained.pipeline.datamanager.next_train(10)
    selected = torch.sigmoid(model.gauss_params["mask_logit"]).squeeze(-1) >= model.config.deform_mask_threshold
    assert 0 < int(selected.sum()) < model.num_points
    results = {}
    for mode in ("gather", "masked"):
        model.config = replace(model.config, deform_subset=mode)
        assert model.masked_deformation() == (mode == "masked")
        results[mode] = _forward(trained, camera, batch)
    model.config = replace(model.config, deform_subset="auto")
    assert "loss motion" in results["gather"] and "loss blur" in results["gather"]
    assert results["gather"].keys() == results["masked"].keys()
    for key, value in results["gather"].items():
        assert_close(results["masked"][key], value, rtol=1e-4, atol=1e-6, msg=key)


def test_the_pair_renders_as_its_cameras_one_by_one(trained) -> None:
    model = trained.pipeline.model
    camera, _ = trained.pipeline.datamanager.next_train(11)
    with torch.no_grad():
        both = model.render_cameras(camera)
        for c in range(2):
            one = model.render_cameras(camera[c : c + 1])
            for key in ("rgb", "mask", "depth", "accumulation"):
                assert_close(both[key][c], one[key][0], rtol=1e-5, atol=1e-5)

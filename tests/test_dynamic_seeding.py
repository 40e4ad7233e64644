"""Motion evidence, dynamic seeds, appending Gaussians and the dynamic-phase time curriculum."""

from __future__ import annotations

import math

import pytest
import torch

from edygs_ns.model.dynamic_seeding import (
    DynamicSeedingConfig, evidence_track, filter_size, fit_motion, motion_evidence, seed_gaussians,
)
from edygs_ns.model.appearance import SH_C0
from edygs_ns.model.gaussians import GAUSSIAN_ATTRIBUTES, init_gaussians, seed_tensors
from edygs_ns.model.strategy import DensifyConfig, append_gaussians, make_strategy
from edygs_ns.model.phases import PhaseSchedule, time_window

pytestmark = pytest.mark.usefixtures("one_thread")

H, W, N = 48, 64, 6


def _residuals() -> tuple:
    """Blotchy texture-like noise, a thin line (pose-error edge) and a moving 12 px blob per latent."""
    gen = torch.Generator().manual_seed(0)
    coarse = 0.08 * torch.rand(N, H // 4, W // 4, generator=gen)
    residual = coarse.repeat_interleave(4, dim=1).repeat_interleave(4, dim=2) + 0.02 * torch.rand(N, H, W, generator=gen)
    residual[:, 10, :] += 0.2  # one-pixel edge in every latent
    blob = torch.zeros(N, H, W, dtype=torch.bool)
    for i in range(N):
        c = 10 + 7 * i
        blob[i, 24:36, c : c + 12] = True
    residual[blob] += 0.3
    return residual, blob


def test_evidence_finds_the_moving_blob_not_the_thin_edge():
    residual, blob = _residuals()
    evidence, threshold, _ = motion_evidence(residual, DynamicSeedingConfig())
    assert threshold >= DynamicSeedingConfig().min_threshold
    hit = evidence.bool()
    iou = (hit & blob).sum() / (hit | blob).sum()
    assert iou > 0.6, float(iou)
    assert not hit[:, 10, 20:44].any()  # the thin edge is averaged away by the box filter
    assert filter_size(128, 0.055) == 7 and filter_size(20, 0.01) == 3


def test_evidence_grows_from_the_contrasted_core_over_the_whole_object():
    """An object whose colour differs strongly from the background only in its centre is found whole
    (hysteresis), while an equally weak patch with no strong pixel stays no evidence."""
    gen = torch.Generator().manual_seed(2)
    blocks = 0.04 + 0.02 * torch.randint(0, 2, (N, H // 4, W // 4), generator=gen).float().mul(2).sub(1)
    residual = blocks.repeat_interleave(4, dim=1).repeat_interleave(4, dim=2)  # 0.02 / 0.06 patches
    body = torch.zeros(N, H, W, dtype=torch.bool)
    body[:, 16:32, 12:28] = True
    residual[body] += 0.07  # weak everywhere on the object ...
    residual[:, 21:27, 17:23] += 0.3  # ... strong in its centre
    residual[:, 18:30, 46:58] += 0.04  # a weak patch elsewhere
    grown, threshold, _ = motion_evidence(residual, DynamicSeedingConfig())
    plain = motion_evidence(residual, DynamicSeedingConfig(grow_mads=10.0)).mask
    hit = grown.bool()
    found, found_plain = float((hit & body).sum() / body.sum()), float((plain.bool() & body).sum() / body.sum())
    assert found > 0.6 and found > 1.5 * found_plain, (found, found_plain)
    assert not hit[:, 18:30, 46:58].any()


def _large_mover(level: float) -> tuple:
    """Half-normal background noise (σ 0.02) and a disc covering a third of each latent, its residual
    ``level`` over the background and strong (+0.25) only in its centre."""
    gen = torch.Generator().manual_seed(0)
    residual = (0.02 * torch.randn(N, H, W, generator=gen)).abs()
    yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    disc = torch.zeros(N, H, W, dtype=torch.bool)
    for i in range(N):
        r2 = (xx - 22 - 3 * i) ** 2 + (yy - 24) ** 2
        disc[i] = r2 < 18**2
        residual[i][disc[i]] += level
        residual[i][r2 < 5**2] += 0.25
    return residual, disc


def test_a_large_mover_grows_on_the_background_levels():
    """A mover over a third of the image inflates the clip's σ_MAD, so the levels taken over all
    values stop the growth inside it; the background's levels grow it whole. Small movers leave
    the clip's σ alone and their evidence is the same either way."""
    residual, disc = _large_mover(0.021)
    iou = {}
    for ratio in (0.0, DynamicSeedingConfig().background_sigma_ratio):  # 0: never the background's levels
        hit = motion_evidence(residual, DynamicSeedingConfig(background_sigma_ratio=ratio)).mask.bool()
        iou[ratio] = float((hit & disc).sum() / (hit | disc).sum())
    assert iou[0.0] < 0.5 and iou[DynamicSeedingConfig().background_sigma_ratio] > 0.8, iou
    large = motion_evidence(residual, DynamicSeedingConfig())
    assert large.background_ratio is not None and large.background_ratio < 0.7
    assert "background's levels" in large.summary()
    small, _ = _residuals()
    kept = motion_evidence(small, DynamicSeedingConfig())
    assert kept.background_ratio is None and "background" not in kept.summary()
    assert torch.equal(kept.mask, motion_evidence(small, DynamicSeedingConfig(background_sigma_ratio=0.0)).mask)


def test_evidence_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"\[N, H, W\]"):
        motion_evidence(torch.zeros(H, W), DynamicSeedingConfig())


def test_seeds_project_back_onto_their_pixels_in_front_of_the_surface():
    cfg = DynamicSeedingConfig(depth_scale=0.9, seed_shape="flat")
    K = torch.tensor([[50.0, 0.0, W / 2], [0.0, 50.0, H / 2], [0.0, 0.0, 1.0]])
    angle = 0.3
    c2w = torch.eye(4)
    c2w[:3, :3] = torch.tensor([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]])
    c2w[:3, 3] = torch.tensor([1.0, -2.0, 0.5])
    evidence = torch.zeros(H, W)
    evidence[20:25, 30:36] = 1.0
    depth = torch.full((H, W), 4.0)
    rgb = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(1))
    points, colors, radii, _ = seed_gaussians(evidence, depth, rgb, K, c2w, cfg)
    assert points.shape == (30, 3) and colors.shape == (30, 3) and radii.shape == (30,)
    cam = (points - c2w[:3, 3]) @ c2w[:3, :3]  # world -> camera (OpenCV)
    assert torch.allclose(cam[:, 2], torch.full((30,), 3.6), atol=1e-5)
    u = cam[:, 0] / cam[:, 2] * K[0, 0] + K[0, 2] - 0.5
    v = cam[:, 1] / cam[:, 2] * K[1, 1] + K[1, 2] - 0.5
    assert torch.allclose(u, u.round(), atol=1e-4) and torch.allclose(v, v.round(), atol=1e-4)
    assert set(v.round().long().tolist()) == set(range(20, 25)) and set(u.round().long().tolist()) == set(range(30, 36))
    assert torch.equal(colors, rgb[v.round().long(), u.round().long()])
    assert torch.allclose(radii, torch.full((30,), cfg.scale_pixels * 3.6 / 50.0))
    few = seed_gaussians(evidence, depth, rgb, K, c2w, DynamicSeedingConfig(max_seeds=7))[0]
    assert few.shape == (7, 3)


def test_cap_seeds_lie_on_a_sphere_of_the_blob_radius_and_project_onto_their_pixels():
    K = torch.tensor([[60.0, 0.0, W / 2], [0.0, 60.0, H / 2], [0.0, 0.0, 1.0]])
    c2w = torch.eye(4)
    c2w[:3, 3] = torch.tensor([0.5, 0.0, -1.0])
    vv, uu = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    evidence = (((vv - 24.0) ** 2 + (uu - 30.0) ** 2) <= 8.0**2).float()  # round blob, radius ~8 px
    depth = torch.full((H, W), 5.0)
    cfg = DynamicSeedingConfig(depth_scale=0.8, seed_shape="cap")
    seeds = seed_gaussians(evidence, depth, torch.rand(H, W, 3), K, c2w, cfg)
    count = int(evidence.sum())
    assert seeds.points.shape == (count, 3)
    z_centre = 0.8 * 5.0
    radius = math.sqrt(count / math.pi) * z_centre / 60.0
    # the centre sits on the blob's mean pixel at the centre depth, the seeds on the near half-sphere
    cam_centre = seeds.centre - c2w[:3, 3]
    assert abs(float(cam_centre[2]) - z_centre) < 1e-5
    assert abs(float(cam_centre[0] / cam_centre[2] * 60.0 + W / 2 - 0.5) - 30.0) < 1e-4
    cam = seeds.points - c2w[:3, 3]
    assert float(cam[:, 2].min()) == pytest.approx(z_centre - radius, rel=0.02)
    assert float(cam[:, 2].max()) <= z_centre + 1e-5
    inner = (seeds.points - seeds.centre).norm(dim=-1) <= radius * 1.05
    assert inner.float().mean() > 0.95
    u = cam[:, 0] / cam[:, 2] * 60.0 + W / 2 - 0.5
    assert torch.allclose(u, u.round(), atol=1e-3)
    # a nearer cap gives smaller seeds: radii follow the seed's own depth
    assert torch.allclose(seeds.radii, cfg.scale_pixels * cam[:, 2] / 60.0, atol=1e-6)


def test_append_keeps_optimizer_and_densification_state_aligned():
    params = init_gaussians(torch.randn(10, 3), None, sh_degree=1, init_opacity=0.1, init_mask=0.1)
    optimizers = {name: torch.optim.Adam([params[name]], lr=1e-3) for name in GAUSSIAN_ATTRIBUTES}
    for name in GAUSSIAN_ATTRIBUTES:
        params[name].grad = torch.ones_like(params[name])
        optimizers[name].step()
    strategy = make_strategy(DensifyConfig())
    state = strategy.initialize_state(scene_scale=1.0)
    state["grad2d"] = torch.arange(10.0)
    state["count"] = torch.ones(10)
    old_means = params["means"].detach().clone()
    new = seed_tensors(torch.zeros(4, 3), torch.full((4, 3), 0.25), torch.full((4,), 0.01), 1, opacity=0.5, mask=0.9)
    assert append_gaussians(params, optimizers, state, new) == 4
    for name in GAUSSIAN_ATTRIBUTES:
        p = params[name]
        assert p.shape[0] == 14 and optimizers[name].param_groups[0]["params"][0] is p
        st = optimizers[name].state[p]
        assert st["exp_avg"].shape == p.shape and torch.all(st["exp_avg"][10:] == 0) and torch.all(st["exp_avg"][:10] != 0)
    assert torch.equal(params["means"][:10], old_means)
    assert torch.allclose(torch.sigmoid(params["mask_logit"][10:]), torch.tensor(0.9))
    assert torch.allclose(torch.sigmoid(params["opacities"][10:]), torch.tensor(0.5))
    assert torch.allclose(params["features_dc"][10:] * SH_C0 + 0.5, torch.tensor(0.25))
    assert torch.equal(state["grad2d"], torch.cat([torch.arange(10.0), torch.zeros(4)])) and state["count"].shape == (14,)


def test_time_window_grows_from_the_reference_to_the_whole_clip():
    s = PhaseSchedule(pose_init_iters=10, static_iters=20, dynamic_window_start=0.1, dynamic_window_ramp_iters=40)
    assert time_window(29, s, 0.5) is None  # static phase: whole clip
    assert time_window(30, s, 0.5) == pytest.approx((0.4, 0.6))
    assert time_window(50, s, 0.5) == pytest.approx((0.2, 0.8))
    assert time_window(70, s, 0.5) is None
    lo, hi = time_window(50, s, 0.2)
    assert hi - 0.2 == pytest.approx(0.1 + (0.8 - 0.1) * 0.5) and lo < 0.0
    assert time_window(30, PhaseSchedule(10, 20, dynamic_window_start=0.5), 0.5) is None


def test_track_and_motion_fit_recover_a_rigid_motion():
    from edygs_ns.model.deformation import DeformationConfig, DeformationField

    n = 5
    K = torch.tensor([[50.0, 0.0, W / 2], [0.0, 50.0, H / 2], [0.0, 0.0, 1.0]])
    cams = torch.eye(4).repeat(n, 1, 1)
    evidence = torch.zeros(n, H, W)
    for i in range(n):
        evidence[i, 20:26, 8 + 10 * i : 14 + 10 * i] = 1.0  # blob moving right 10 px per latent
    evidence[2, 0, 0] = 1.0  # a stray pixel is outvoted by the blob
    evidence[3] = 0.0
    evidence[3, 5, 5] = 1.0  # too few pixels: no track point
    depth = torch.full((n, H, W), 2.0)
    idx, track = evidence_track(evidence, depth, K.repeat(n, 1, 1), cams, DynamicSeedingConfig(depth_scale=1.0))
    assert idx.tolist() == [0, 1, 2, 4]
    step = 10 * 2.0 / 50.0  # 10 px at depth 2, f = 50
    assert torch.allclose(track[1] - track[0], torch.tensor([step, 0.0, 0.0]), atol=1e-5)
    assert torch.allclose(track[3] - track[0], torch.tensor([4 * step, 0.0, 0.0]), atol=1e-5)

    field = DeformationField(DeformationConfig(depth=3, width=32, skip_layer=1, xyz_frequencies=2, time_frequencies=3))
    seeds = torch.randn(40, 3, generator=torch.Generator().manual_seed(0)) * 0.05 + track[0]
    times = torch.tensor([0.0, 0.25, 0.5, 1.0])
    offsets = track - track[0]
    cfg = DynamicSeedingConfig(init_motion_steps=300, init_motion_lr=3e-3)
    losses = fit_motion(field, seeds, times, offsets, cfg)
    assert len(losses) == 300 and losses[-1] < 0.05 * losses[0]
    with torch.no_grad():
        d_xyz, _, _ = field(seeds, 1.0)
    assert torch.allclose(d_xyz.mean(0), offsets[3], atol=0.05 * float(offsets[3].norm()))
    assert all(p.grad is None for p in field.parameters())

"""Finding, seeding and tracking every moving object at the dynamic switch (model/motion_init.py)."""

from __future__ import annotations

import math

import pytest
import torch

from edygs_ns.model.dynamic_seeding import DynamicSeedingConfig
from edygs_ns.model.motion_init import (apart_latent, evidence_regions, initialise_motion, parts_diverge, split_at_necks, strays_far,
                                        verdict)
from edygs_ns.model.rigid_track import RigidTrack
from edygs_ns.model.rigid_track import RigidTrackConfig
from edygs_ns.render.torch_backend import rasterize_torch

pytestmark = pytest.mark.usefixtures("one_thread")

H, W, F = 48, 64, 60.0
N, REF = 9, 4
DEPTH = 3.0
RADIUS = 0.35
BACKGROUND = 0.4


def _ball(centre: torch.Tensor, seed: int, count: int = 1500):
    """Points on a sphere of RADIUS about ``centre`` with a blocky random texture, and their radii."""
    i = torch.arange(count, dtype=torch.float32) + 0.5
    polar = torch.arccos(1 - 2 * i / count)
    azimuth = math.pi * (1 + 5**0.5) * i
    dirs = torch.stack([polar.sin() * azimuth.cos(), polar.cos(), polar.sin() * azimuth.sin()], dim=-1)
    cells = (torch.floor(polar * 4) * 17 + torch.floor(azimuth % (2 * math.pi) * 3)).long()
    palette = torch.rand(200, 3, generator=torch.Generator().manual_seed(seed))
    return centre + RADIUS * dirs, palette[cells % 200], torch.full((count,), 0.015)


def _clip(shifts: list, apart: float = 0.6):
    """N latents of a static camera watching balls that move by ``shifts`` [3] per latent each
    (zero: a still ball), at x = ∓``apart`` in the reference latent; returns latents, evidence (the
    union of the balls' silhouettes), the static background render, depth, viewmats, cams_to_world,
    Ks and times."""
    starts = [torch.tensor([-apart, 0.0, DEPTH]), torch.tensor([apart, 0.0, DEPTH])]
    balls = [_ball(start, seed=k) for k, start in enumerate(starts[: len(shifts)])]
    K = torch.tensor([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])
    eye = torch.eye(4)
    background = torch.full((H, W, 3), BACKGROUND)
    vv, uu = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    rays = torch.nn.functional.normalize(torch.stack([(uu - W / 2) / F, (vv - H / 2) / F, torch.ones_like(uu)], -1), dim=-1)
    latents, evidence = [], []
    for i in range(N):
        image, silhouettes = background.clone(), torch.zeros(H, W, dtype=torch.bool)
        for (points, colors, radii), shift, start in zip(balls, shifts, starts):
            moved = points + (i - REF) * torch.tensor(shift)
            quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(len(points), 1)
            out = rasterize_torch(moved, quats, radii[:, None].repeat(1, 3), torch.full((len(points),), 0.95), colors,
                                  eye[None], K[None], W, H)
            image = out.render[0] + (1 - out.alpha[0]) * image
            centre = start + (i - REF) * torch.tensor(shift)
            along = rays @ centre
            silhouettes |= (centre.square().sum() - along.square()) < RADIUS**2
        latents.append(image)
        evidence.append(silhouettes.float())
    n = torch.arange(N, dtype=torch.float32)
    depth = torch.full((N, H, W), DEPTH / 0.9)  # the seeds' cap centre lands at the balls' depth
    return (torch.stack(latents), torch.stack(evidence), background.expand(N, H, W, 3), depth, eye.repeat(N, 1, 1),
            eye.repeat(N, 1, 1), K.repeat(N, 1, 1), n / (N - 1))


def _initialise(latents, evidence, statics, depth, viewmats, c2w, Ks, times, seeding=DynamicSeedingConfig()):
    return initialise_motion(evidence, depth, statics, lambda i: latents[i], viewmats, c2w, Ks, times, REF, rasterize_torch,
                             seeding, RigidTrackConfig(steps=30))


def test_evidence_regions_are_separate_and_ordered_by_size():
    evidence = torch.zeros(20, 30)
    evidence[2:6, 2:6] = 1  # 16 px
    evidence[10:18, 15:25] = 1  # 80 px
    evidence[0, 29] = 1  # 1 px: noise
    regions = evidence_regions(evidence, min_pixels=4)
    assert [int(r.sum()) for r in regions] == [80, 16]
    assert not bool((regions[0] & regions[1]).any())


def test_two_objects_are_found_apart_and_each_gets_its_own_track():
    shifts = [[0.15, 0.0, 0.0], [0.0, 0.15, 0.0]]  # the left ball goes right, the right ball goes down
    latents, evidence, statics, depth, viewmats, c2w, Ks, times = _clip(shifts)
    found = _initialise(latents, evidence, statics, depth, viewmats, c2w, Ks, times)
    movers = found.movers
    assert len(movers) == 2, [o.summary() for o in found.objects]
    assert all(o.verdict == "" for o in movers)
    movers = sorted(movers, key=lambda o: float(o.track.centre[0]))  # left ball first
    project = lambda p: p[..., :2] / p[..., 2:] * F  # noqa: E731  (a static camera at the origin)
    for obj, shift, start in zip(movers, shifts, (-0.6, 0.6)):
        true = torch.tensor([start, 0.0, DEPTH]) + (torch.arange(N, dtype=torch.float32) - REF)[:, None] * torch.tensor(shift)
        tracked = obj.track.centre + obj.track.translations
        # a static camera cannot tell depth from size: compare where the centres project (pixels)
        error = (project(tracked) - project(true)).norm(dim=-1)
        moved = (project(true) - project(true[REF])).norm(dim=-1)
        assert float(error.max()) < 0.35 * float(moved.max()), (project(tracked), project(true))
    # each body is centred on its own ball and reaches no farther than the gap to the other one
    for obj, x in zip(movers, (-0.6, 0.6)):
        assert abs(float(obj.track.centre[0]) - x) < 0.15 and obj.reach < 1.2
    assert len(found.seed_tensors().points) == sum(len(o.seeds.points) for o in movers)
    # M̂ is the evidence near the tracked objects: here all of it
    assert torch.equal(found.consistency, evidence)


def _two_balls(shifts: list, apart: float, regions: int):
    """The clip of two balls ``apart`` (``_clip``), whose reference latent holds ``regions``
    evidence regions, and its two movers, left first (asserted to be two)."""
    clip = _clip(shifts, apart=apart)
    assert len(evidence_regions(clip[1][REF], 10)) == regions
    found = _initialise(*clip)
    movers = sorted(found.movers, key=lambda o: float(o.track.centre[0]))
    assert len(movers) == 2, [o.summary() for o in found.objects]
    return clip, movers


def test_an_object_inside_anothers_claimed_zone_is_found_too():
    # two balls two pixels apart in the reference latent (two regions), the second inside the
    # first's claimed zone (its silhouette plus a radius), going opposite ways: each is seeded and
    # tracked from its whole region (not from what the first one's zone leaves of it, which fits
    # its ball with IoU 0.40)
    shifts = [[-0.12, 0.0, 0.0], [0.12, 0.0, 0.0]]
    _, movers = _two_balls(shifts, apart=RADIUS * 1.15, regions=2)
    assert all(o.ref == REF for o in movers)
    for obj in movers:
        iou = obj.track.iou[torch.isfinite(obj.track.iou)]
        assert float(iou.mean()) > 0.6, obj.summary()
    for obj, shift in zip(movers, shifts):
        travelled = obj.track.translations[-1] - obj.track.translations[0]
        assert float(travelled[0]) * shift[0] > 0  # each body goes its own ball's way


def _discs(*circles) -> torch.Tensor:
    """A [40, 60] bool mask: the union of discs (row, col, radius in pixels)."""
    rows, cols = torch.meshgrid(torch.arange(40.0), torch.arange(60.0), indexing="ij")
    mask = torch.zeros(40, 60, dtype=torch.bool)
    for r, c, radius in circles:
        mask |= (rows - r) ** 2 + (cols - c) ** 2 <= radius**2
    return mask


def test_a_region_is_cut_at_its_neck_and_a_round_one_is_not():
    touching = _discs((20, 18, 9), (20, 36, 8)) | (_discs((20, 27, 2)))  # two blobs and a thin bridge
    parts = split_at_necks(touching, neck_fraction=0.25, min_pixels=10)
    assert len(parts) == 2
    assert torch.equal(parts[0] | parts[1], touching) and not bool((parts[0] & parts[1]).any())
    assert int(parts[0].sum()) > int(parts[1].sum())  # largest first
    assert bool(parts[0][20, 18]) and bool(parts[1][20, 36])
    # a disc, a disc with a bump, and a split whose smaller part is under min_pixels stay whole
    assert len(split_at_necks(_discs((20, 30, 12)), 0.25, 10)) == 1
    assert len(split_at_necks(_discs((20, 30, 12), (20, 42, 3)), 0.25, 10)) == 1
    assert len(split_at_necks(touching, 0.25, min_pixels=300)) == 1
    small = _discs((20, 18, 11), (20, 37, 6)) | _discs((20, 30, 2))  # the small side: under a quarter
    assert len(split_at_necks(small, 0.25, 10, min_share=0.1)) == 2
    assert len(split_at_necks(small, 0.25, 10, min_share=0.25)) == 1
    assert len(split_at_necks(touching, 0.0, 10)) == 1


def _translated(steps: list) -> RigidTrack:
    translations = torch.tensor(steps, dtype=torch.float32)
    return RigidTrack(torch.zeros(3), torch.zeros_like(translations), translations, torch.zeros(len(steps)))


def test_parts_diverge_only_when_their_tracks_move_apart():
    left, right = _translated([[0, 0, 0], [-1, 0, 0], [-2, 0, 0]]), _translated([[0, 0, 0], [1, 0, 0], [2, 0, 0]])
    together = _translated([[0, 0, 0], [-1.1, 0, 0], [-1.9, 0, 0]])
    assert parts_diverge([left, right], [0.5, 0.5], divergence=1.0)  # 4 apart > 1
    assert not parts_diverge([left, together], [0.5, 0.5], divergence=1.0)  # 0.1 apart
    assert not parts_diverge([left, right], [2.5, 2.5], divergence=1.0)  # big parts: 4 < 5


def test_two_touching_objects_are_cut_apart_and_each_tracked():
    # the balls touch in the reference latent (one evidence region) and leave each other
    shifts = [[-0.12, 0.0, 0.0], [0.12, 0.04, 0.0]]
    clip, movers = _two_balls(shifts, apart=RADIUS * 1.05, regions=1)
    assert all(o.cut == "neck" and "cut at a neck" in o.summary() for o in movers)
    for obj, shift in zip(movers, shifts):
        travelled = obj.track.translations[-1] - obj.track.translations[0]
        assert float(travelled[0]) * shift[0] > 0  # each body goes its own object's way
    # without the cut (nor the later look for latents where it falls apart), one track follows the
    # joined region: one mover
    whole = _initialise(*clip, DynamicSeedingConfig(neck_fraction=0.0, apart_presence=2.0))
    assert len(whole.movers) == 1, [o.summary() for o in whole.objects]
    assert not any(o.cut for o in whole.objects)


def test_two_objects_overlapping_in_the_reference_latent_are_told_apart_where_they_part():
    # the balls overlap in the reference latent (one round region, no neck) and leave each other:
    # the joined region's mover is tracked again as two from a latent where they are apart
    shifts = [[-0.12, 0.0, 0.0], [0.12, 0.04, 0.0]]
    clip, movers = _two_balls(shifts, apart=RADIUS * 0.5, regions=1)
    assert all(o.cut == "apart" and "apart in this latent" in o.summary() for o in movers)
    assert all(o.ref != REF for o in movers)
    for obj, shift in zip(movers, shifts):
        travelled = obj.track.translations[-1] - obj.track.translations[0]
        assert float(travelled[0]) * shift[0] > 0  # each body goes its own object's way
    whole = _initialise(*clip, DynamicSeedingConfig(apart_presence=2.0))
    assert len(whole.movers) == 1, [o.summary() for o in whole.objects]


def test_apart_latent_picks_the_most_even_split_of_a_lasting_one():
    zone = torch.zeros(5, 20, 30, dtype=torch.bool)
    zone[:, 5:12, 5:12] = True  # 49 px in every latent
    zone[1, 5:12, 20:24] = True  # a second part of 28 px
    zone[3, 5:12, 18:25] = True  # ... of 49 px: the most even
    zone[4, 0:2, 28:30] = True  # 4 px: too small to count
    latent, parts = apart_latent(zone, min_pixels=10, min_share=0.25, min_latents=2)
    assert latent == 3 and [int(p.sum()) for p in parts] == [49, 49]
    assert apart_latent(zone, min_pixels=10, min_share=0.25, min_latents=3) is None, "apart in two latents only"
    assert apart_latent(zone, min_pixels=10, min_share=0.45, min_latents=1)[0] == 3, "28 of 77 px is under 45 %"


def test_a_still_region_is_no_mover_and_seeds_nothing():
    # one ball that never moves, which the "static model" (the plain background) fails to explain
    latents, evidence, statics, depth, viewmats, c2w, Ks, times = _clip([[0.0, 0.0, 0.0]])
    found = _initialise(latents, evidence, statics, depth, viewmats, c2w, Ks, times)
    assert len(found.objects) >= 1 and not found.movers
    assert len(found.seed_tensors().points) == 0
    # the log says why: the ball is tracked in every latent but never leaves its place
    assert "strays" in found.objects[0].verdict and "under the" in found.objects[0].summary(), found.objects[0].summary()
    assert float(found.consistency.sum()) == 0.0


def test_a_slow_object_held_in_every_latent_is_a_mover():
    """A ball whose rigid silhouette holds in every latent, travelling less than its radius asks
    (here a whole radius, 7 px, capped at 7 % of the width: 4.5 px) but more than the 5 % floor
    (3.2 px), is a mover; without the held rule (``held_presence`` above 1) it is not."""
    step = 3.9 / (REF * F / DEPTH)  # 3.9 px from the reference position at the clip's ends
    latents, evidence, statics, depth, viewmats, c2w, Ks, times = _clip([[step, 0.0, 0.0]])
    seeding = DynamicSeedingConfig(still_shift=1.0)
    found = _initialise(latents, evidence, statics, depth, viewmats, c2w, Ks, times, seeding)
    assert len(found.movers) == 1, [o.summary() for o in found.objects]
    strict = _initialise(latents, evidence, statics, depth, viewmats, c2w, Ks, times,
                         DynamicSeedingConfig(still_shift=1.0, held_presence=2.0))
    assert not strict.movers and "strays" in strict.objects[0].verdict, [o.summary() for o in strict.objects]


def test_no_evidence_no_objects():
    latents, _, statics, depth, viewmats, c2w, Ks, times = _clip([])
    found = _initialise(latents, torch.zeros(N, H, W), statics, depth, viewmats, c2w, Ks, times)
    assert found.objects == [] and len(found.seed_tensors().points) == 0
    assert float(found.consistency.sum()) == 0.0


def test_a_big_object_need_not_travel_its_radius():
    """The shift a mover needs is half its radius, but at least 5 % and at most 7 % of the image width."""
    cfg = DynamicSeedingConfig()
    assert strays_far(9.5, radius_px=30.0, width=128, seeding=cfg)  # a quarter of the image, 9.5 px
    assert not strays_far(8.5, radius_px=30.0, width=128, seeding=cfg)
    assert not strays_far(5.0, radius_px=3.0, width=128, seeding=cfg)  # a few pixels: track jitter
    half = cfg.still_shift * 14.0  # between the floor and the cap, half the radius (still_shift 0.5)
    assert strays_far(half + 0.5, radius_px=14.0, width=128, seeding=cfg) and not strays_far(half - 0.5, radius_px=14.0, width=128, seeding=cfg)
    # a region kept on its presence alone (poor rigid fit) must stray a whole radius (up to the cap)
    assert not strays_far(half + 0.5, radius_px=14.0, width=128, seeding=cfg, radii=cfg.steady_shift)
    # a rigid silhouette held through most of the clip needs only the floor, whatever its size
    floor = cfg.still_shift_fraction * 128
    assert strays_far(floor + 0.5, radius_px=30.0, width=128, seeding=cfg, held=True)
    assert not strays_far(floor - 0.5, radius_px=30.0, width=128, seeding=cfg, held=True)


def test_verdict_names_the_first_failed_test():
    cfg = DynamicSeedingConfig()
    ok = dict(presence=1.0, mean_iou=0.6, rigid_fit=True, steady=True, shift_px=20.0, needed_px=10.0, duplicate=False, seeding=cfg)
    assert verdict(**ok) == ""
    assert "of the latents" in verdict(**dict(ok, presence=0.1, shift_px=0.0))  # presence comes first
    assert "IoU 0.10" in verdict(**dict(ok, mean_iou=0.1, rigid_fit=False, presence=0.5))
    assert verdict(**dict(ok, mean_iou=0.2, rigid_fit=False)) == ""  # kept on presence (steady)
    assert "under 0.15 for a region found in most latents" in verdict(**dict(ok, mean_iou=0.1, rigid_fit=False))  # drifted off
    assert "20.0 px" in verdict(**dict(ok, needed_px=30.0))
    assert "found before" in verdict(**dict(ok, duplicate=True))
    # evidence where few training views see the static scene: a poorly fitted static model there
    assert "few training views" in verdict(**dict(ok, support=0.4)) and "0.40" in verdict(**dict(ok, support=0.4))
    assert verdict(**dict(ok, support=0.7)) == ""

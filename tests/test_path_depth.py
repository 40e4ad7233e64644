"""A moving object's depth from the shape of its path (model/path_depth.py)."""

from __future__ import annotations

from dataclasses import replace

import torch

from edygs_ns.model.dynamic_seeding import DynamicSeedingConfig, Seeds
from edygs_ns.model.path_depth import clamped_factor, latent_factors, path_depth, rescale, simplest_path, triangulate_path
from edygs_ns.model.rigid_track import RigidTrack, rigid_apply, rotation_matrices

N = 40
TIMES = torch.linspace(0.0, 1.0, N)


def _eyes(times: torch.Tensor) -> torch.Tensor:
    """A camera sweeping an arc (its path bends; a straight one would not decide the depth)."""
    return torch.stack([0.6 * torch.sin(3.0 * times), 0.2 * torch.cos(3.0 * times), 1.5 - 0.3 * times], dim=-1)


def _object_path(times: torch.Tensor) -> torch.Tensor:
    """An object moving at constant acceleration in front of the camera."""
    return torch.stack([-0.5 + 1.0 * times, -0.2 + 0.4 * times**2, -2.0 + 0.3 * times], dim=-1)


def test_triangulation_finds_the_distance_of_a_polynomial_path():
    eyes, path = _eyes(TIMES), _object_path(TIMES)
    rays = path - eyes
    distance, residual, condition = triangulate_path(eyes, rays, TIMES, degree=2)
    assert condition > 1e-4 and float(residual) < 1e-6
    assert torch.allclose(distance, rays.norm(dim=-1), rtol=1e-4)


def test_a_still_camera_decides_no_depth():
    eyes = torch.zeros(N, 3)
    rays = _object_path(TIMES) - eyes
    _, _, condition = triangulate_path(eyes, rays, TIMES, degree=2)
    assert condition < 1e-6
    track = RigidTrack(rays[0], torch.zeros(N, 3), rays - rays[0], torch.zeros(N), iou=torch.ones(N))
    assert path_depth(track, 0.1, eyes, TIMES) is None


def test_a_track_placed_too_far_is_brought_back_to_its_path():
    eyes, truth = _eyes(TIMES), _object_path(TIMES)
    ref = N // 2
    too_far = eyes + 1.4 * (truth - eyes)  # what the seeding at the static depth would give
    centre = too_far[ref]
    iou = torch.ones(N)
    iou[:5] = float("nan")  # latents where the object was not seen do not count
    track = RigidTrack(centre, 0.02 * torch.arange(N, dtype=torch.float32)[:, None] * torch.tensor([0.0, 1.0, 0.0]),
                       too_far - centre, torch.zeros(N), iou=iou)
    fit = path_depth(track, 0.1, eyes, TIMES, turns=False)
    assert fit is not None and abs(fit.factor - 1 / 1.4) < 1e-3 and fit.residual < 1e-3
    factor = fit.factor

    points = centre + 0.1 * torch.randn(50, 3, generator=torch.Generator().manual_seed(0))
    seeds = Seeds(points, torch.rand(50, 3), torch.full((50,), 0.01), centre)
    moved, placed = rescale(track, seeds, eyes, ref, factor)
    assert torch.allclose(moved.centre + moved.translations, truth, atol=1e-4)
    assert torch.allclose(placed.radii, seeds.radii * factor)
    # every latent sees the rescaled object where it saw the old one: same direction from its camera
    before = rigid_apply(seeds.points, track.centre, rotation_matrices(track.rotvecs), track.translations) - eyes[:, None]
    after = rigid_apply(placed.points, moved.centre, rotation_matrices(moved.rotvecs), moved.translations) - eyes[:, None]
    assert torch.allclose(torch.nn.functional.normalize(before, dim=-1), torch.nn.functional.normalize(after, dim=-1), atol=1e-5)
    assert torch.allclose(after.norm(dim=-1), factor * before.norm(dim=-1), rtol=1e-4)


def test_a_spinning_object_is_placed_by_the_point_that_moves_simply():
    """The tracked centre is on the object's front (where its seeds were); spinning, it wobbles
    about the true centre, whose path is the simple one. Searching the body point finds it."""
    eyes, truth = _eyes(TIMES), _object_path(TIMES)
    ref, size = N // 2, 0.1
    front = truth[ref] + torch.tensor([0.0, 0.0, 2.0 * size])  # 2 sizes in front of the centre
    rotvecs = (TIMES - TIMES[ref])[:, None] * torch.tensor([0.0, 3.0, 0.0])  # 170° over the clip
    rotations = rotation_matrices(rotvecs)
    positions = torch.einsum("nij,j->ni", rotations, front - truth[ref]) + truth
    exact = RigidTrack(front, rotvecs, positions - front, torch.zeros(N), iou=torch.ones(N))
    seeds = Seeds(front[None], torch.rand(1, 3), torch.full((1,), 0.01), front)
    too_far, _ = rescale(exact, seeds, eyes, ref, 1.4)
    found = path_depth(too_far, 1.4 * size, eyes, TIMES, turns=True)
    centre_only = path_depth(too_far, 1.4 * size, eyes, TIMES, turns=False)
    assert found is not None and centre_only is not None
    assert abs(found.factor - 1 / 1.4) < 0.01 and found.residual < 0.01
    assert abs(centre_only.factor - 1 / 1.4) > 0.02 and centre_only.residual > 10 * found.residual


def test_a_track_seeded_too_close_is_moved_back_out():
    """Seeded in front of a smear the static phase left nearer than the background, an object sits
    too close; its path says how much farther it is, and the default limits let it go there."""
    eyes, truth = _eyes(TIMES), _object_path(TIMES)
    ref = N // 2
    too_close = eyes + 0.7 * (truth - eyes)
    centre = too_close[ref]
    track = RigidTrack(centre, torch.zeros(N, 3), too_close - centre, torch.zeros(N), iou=torch.ones(N))
    fit = path_depth(track, 0.1, eyes, TIMES, turns=False)
    assert fit is not None and abs(fit.factor - 1 / 0.7) < 1e-3
    factor = clamped_factor(fit, DynamicSeedingConfig().path_depth_range)
    assert abs(factor - 1 / 0.7) < 1e-3
    seeds = Seeds(centre[None], torch.rand(1, 3), torch.full((1,), 0.01), centre)
    moved, _ = rescale(track, seeds, eyes, ref, factor)
    assert torch.allclose(moved.centre + moved.translations, truth, atol=1e-4)
    # the guard still holds a runaway fit
    assert clamped_factor(replace(fit, factor=50.0), DynamicSeedingConfig().path_depth_range) <= 4.0


def _line_path(times: torch.Tensor) -> torch.Tensor:
    """An object moving at constant velocity in front of the camera."""
    return torch.stack([-0.5 + 1.0 * times, -0.2 + 0.1 * times, -2.0 + 0.3 * times], dim=-1)


def _track(positions: torch.Tensor) -> RigidTrack:
    centre = positions[N // 2]
    return RigidTrack(centre, torch.zeros(N, 3), positions - centre, torch.zeros(N), iou=torch.ones(N))


def test_a_noisy_straight_track_takes_the_straight_path():
    """Tracking noise bends the quadratic fit and pulls its depth in towards the cameras; the
    straight path fits the lines of sight about as well and keeps the true depth."""
    eyes, truth = _eyes(TIMES), _line_path(TIMES)
    noise = 0.01 * torch.randn(N, 3, generator=torch.Generator().manual_seed(0))  # a tenth of the object's size
    track = _track(eyes + 1.4 * (truth - eyes) + noise)
    quadratic = path_depth(track, 0.1, eyes, TIMES, turns=False)
    assert quadratic is not None and abs(quadratic.factor - 1 / 1.4) > 0.2  # what the quadratic alone gets
    fit = simplest_path(track, 0.1, eyes, TIMES, False, DynamicSeedingConfig().path_depth_line_ratio, 0.3)
    assert fit is not None and fit.degree == 1
    assert abs(fit.factor - 1 / 1.4) < 0.02
    assert simplest_path(track, 0.1, eyes, TIMES, False, 0.0, 0.3).degree == 2  # ratio 0: the quadratic only


def test_a_bending_track_keeps_the_quadratic_path():
    eyes, truth = _eyes(TIMES), _object_path(TIMES)
    track = _track(eyes + 1.4 * (truth - eyes))
    fit = simplest_path(track, 0.1, eyes, TIMES, False, DynamicSeedingConfig().path_depth_line_ratio, 0.3)
    assert fit is not None and fit.degree == 2 and abs(fit.factor - 1 / 1.4) < 1e-3


def test_a_straight_path_corrects_the_depths_an_image_size_got_wrong():
    """A deforming object's image size changes with its shape, and the tracker reads that as
    depth: every latent off by its own factor. On a straight path each latent moves the
    configured share (geometric) of the way onto the path's distance; a latent the track did not
    see takes its nearest seen neighbour's factor."""
    eyes, truth = _eyes(TIMES), _line_path(TIMES)
    wrong = 1.4 * (1.0 + 0.3 * torch.sin(2.0 * torch.pi * TIMES))  # per-latent depth error of the tracker
    track = _track(eyes + wrong[:, None] * (truth - eyes))
    track.iou[-3:] = float("nan")  # not seen at the end of the clip
    limits = DynamicSeedingConfig().path_depth_range
    fit = simplest_path(track, 0.1, eyes, TIMES, False, DynamicSeedingConfig().path_depth_line_ratio, 0.3)
    assert fit is not None and fit.degree == 1 and fit.residual < 1e-3
    seen = torch.isfinite(track.iou)
    assert torch.allclose(fit.ratios[seen], 1.0 / wrong[seen], rtol=1e-3) and bool(fit.ratios[~seen].isnan().all())
    points = Seeds(track.centre[None], torch.rand(1, 3), torch.full((1,), 0.01), track.centre)

    def log_error(follow: float) -> torch.Tensor:
        factors = latent_factors(fit, limits, follow, TIMES)
        moved, _ = rescale(track, points, eyes, N // 2, factors)
        return ((moved.centre + moved.translations - eyes).norm(dim=-1) / (truth - eyes).norm(dim=-1)).log().abs()

    one, half, whole = log_error(0.0), log_error(0.5), log_error(1.0)
    assert float(one[seen].max()) > 0.2  # one factor keeps the tracker's latent-to-latent errors
    assert torch.allclose(half[seen], 0.5 * (wrong[seen].log() - wrong[seen].log().median()).abs(), atol=2e-3)
    assert float(whole[seen].max()) < 2e-3
    assert torch.allclose(latent_factors(fit, limits, 1.0, TIMES)[-3:], latent_factors(fit, limits, 1.0, TIMES)[-4])


def test_a_curved_path_moves_every_latent_by_one_factor():
    """A quadratic is a loose model of a curve (a circle, a swing): the tracker's own
    latent-to-latent depth is kept, whatever the follow share."""
    eyes, truth = _eyes(TIMES), _object_path(TIMES)
    track = _track(eyes + 1.4 * (1.0 + 0.05 * torch.sin(2.0 * torch.pi * TIMES))[:, None] * (truth - eyes))
    fit = path_depth(track, 0.1, eyes, TIMES, turns=False)
    assert fit is not None and fit.degree == 2
    factors = latent_factors(fit, DynamicSeedingConfig().path_depth_range, 0.5, TIMES)
    assert torch.allclose(factors, torch.full((N,), clamped_factor(fit, DynamicSeedingConfig().path_depth_range)))

"""A moving object's depth from the shape of its path (trajectory triangulation).

A rigid object that moves independently is seen from one moving camera at one instant each: put
it twice as far, twice as large, moving along ``e_i + 2 (x_i - e_i)`` (``e_i`` the camera centre
at latent i) and every training view is the same. The photometric losses cannot tell the depth,
and the tracked seeds keep the depth they were placed at (a fraction of the static depth behind
them, i.e. just in front of the background), which is what novel cameras then see wrong (the
object off its true place by the parallax of its depth error).

What does tell the depth is that objects move simply while the camera's path bends: of all the
depth scalings ``e_i + a (x_i - e_i)`` of a tracked path, the true one is the one whose 3D path
is a low-order polynomial in time (trajectory triangulation, Avidan & Shashua 2000). Each
latent's line of sight gives two linear equations on the polynomial's coefficients
(``(X(t_i) - e_i) x r_i = 0``), weighted by one over the fitted distance so that the fit
minimises angles (an unweighted fit favours paths that hug the cameras, where every ray
passes). A turning object's tracked centre (the front of its seeds) wobbles about the point that
moves simply (a ball's centre, an arm's hinge), so the fit is tried for a grid of body points and
the best-fitting one is kept; its factor ``a`` is the median ratio of fitted to tracked distances.
The quadratic is the default path; a straight one is taken when it fits nearly as well
(``simplest_path``: fewer coefficients follow less of the track's noise). ``rescale`` then
applies the factor to the seeds and the track about each latent's camera centre, which leaves
every training view's projection as it was.

One factor keeps the tracker's latent-to-latent depth changes, which come from the object's image
size: right for a rigid object, wrong for one whose size in the image changes with its shape. A
straight path is a strong model of where the object is at each instant, a quadratic a loose one
for a curve (a circle, a swing): so on a straight path each latent's distance goes part of the
way onto the path's own (``latent_factors``), on a curved one the factor is the same for all.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Dict, Optional, Tuple, Union

import torch
from jaxtyping import Float
from torch import Tensor

from edygs_ns.model.dynamic_seeding import Seeds
from edygs_ns.model.rigid_track import RigidTrack, rigid_apply, rotation_matrices

#: Fewest latents with a tracked centre for a path fit (a quadratic in 3D has 9 unknowns).
MIN_PATH_LATENTS = 8
#: Smallest ratio of the path fit's least to largest singular value that decides a depth (under
#: it, e.g. from a still camera, many depths give a polynomial path equally well).
MIN_CONDITION = 1e-4
#: Body points tried as the one with the simplest path: a grid of POINT_STEPS per axis within
#: POINT_REACH object sizes of the track's centre.
POINT_REACH = 2.0
POINT_STEPS = 9
#: Reweighted least-squares rounds of the path fit (each weighs a ray by 1 / its fitted distance).
ANGULAR_ITERATIONS = 4


def _skew(v: Float[Tensor, "N 3"]) -> Float[Tensor, "N 3 3"]:
    """Cross-product matrices [v]x of [N, 3] vectors."""
    zero = torch.zeros_like(v[:, 0])
    return torch.stack([
        torch.stack([zero, -v[:, 2], v[:, 1]], dim=-1),
        torch.stack([v[:, 2], zero, -v[:, 0]], dim=-1),
        torch.stack([-v[:, 1], v[:, 0], zero], dim=-1),
    ], dim=1)  # fmt: skip


def _design(unit: Tensor, basis: Tensor) -> Tuple[Tensor, Tensor]:
    """Per-ray cross-product matrices [B, N, 3, 3] of the unit rays [B, N, 3] and the linear system
    of the path's coefficients, [B, 3N, 3D] for the time basis [N, D]:
    [d]x (sum_j tau^j a_j) = [d]x o for every ray."""
    skew = _skew(unit.reshape(-1, 3)).reshape(*unit.shape[:-1], 3, 3)
    design = (basis[None, :, None, :, None] * skew[:, :, :, None, :]).reshape(unit.shape[0], unit.shape[1] * 3, -1)
    return skew, design


def triangulate_path(origins: Float[Tensor, "N 3"], directions: Float[Tensor, "*B N 3"], times: Float[Tensor, "N"],
                     degree: int = 2) -> Tuple[Float[Tensor, "*B N"], Float[Tensor, "*B"], float]:
    """The polynomial path (in time, of ``degree``) closest to the rays from ``origins`` along
    ``directions``; several sets of directions (a leading batch dimension) fit at once.

    Args:
        origins: camera centres, world units; directions: rays towards the object (any length).
        times: time of every ray (any units; rescaled to [-1, 1] for the fit's conditioning).
        degree: of the path's polynomial in time.

    Returns:
        [*B, N] signed distance from each origin to the fitted path's point at that time, along
        the unit ray; [*B] RMS distance of those points from their rays (world units); and the
        conditioning of the (first) fit (least / largest singular value of its system).
    """
    batched = directions.dim() == 3
    o, d, t = (x.detach().double().cpu() for x in (origins, directions if batched else directions[None], times))
    span = (t.max() - t.min()).clamp_min(1e-12)
    tau = 2.0 * (t - t.min()) / span - 1.0
    basis = torch.stack([tau**j for j in range(degree + 1)], dim=-1)  # [N, D]
    unit = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    skew, design = _design(unit, basis)
    target = (skew @ o[None, :, :, None]).reshape(d.shape[0], -1, 1)
    distance = d.norm(dim=-1)  # [B, N] start: the tracked distances
    for _ in range(ANGULAR_ITERATIONS):
        # rows weighted by 1 / distance: the fit minimises angles (image errors), not lengths,
        # which would favour a path hugging the cameras (every ray passes through its camera)
        floor = 1e-3 * distance.abs().median(dim=1, keepdim=True).values.clamp_min(1e-12)
        weight = (1.0 / distance.abs().clamp_min(floor)).repeat_interleave(3, dim=1)[..., None]
        coefs = torch.linalg.lstsq(design * weight, target * weight).solution  # [B, 3D, 1]
        path = torch.einsum("nj,bjk->bnk", basis, coefs.reshape(d.shape[0], degree + 1, 3))
        distance = ((path - o[None]) * unit).sum(dim=-1)
    residual = ((design @ coefs - target).square().sum(dim=(1, 2)) / len(t)).sqrt()
    values = torch.linalg.svdvals(design[0])
    condition = float(values[-1] / values[0].clamp_min(1e-300))
    if not batched:
        distance, residual = distance[0], residual[0]
    return distance.to(origins.dtype).to(origins.device), residual.to(origins.dtype).to(origins.device), condition


@dataclass
class PathFit:
    """The depth a tracked object's path gives: ``factor`` on its distance from the cameras, the
    fitted path's RMS distance from its lines of sight in object sizes (``residual``), and the
    body point whose path was fitted (``point``, canonical frame, world units), the path's
    polynomial ``degree``, every latent's fitted over tracked distance (``ratios``, [N], NaN where
    the track did not see the object; ``factor`` is their median); ``applied``: the factors
    [N] the motion initialisation moved the object by, None if it did not."""

    factor: float
    residual: float
    point: Tensor
    ratios: Tensor
    degree: int = 2
    applied: Optional[Tensor] = None


def path_depth(track: RigidTrack, size: float, eyes: Float[Tensor, "N 3"], times: Float[Tensor, "N"],
               turns: bool = True, degree: int = 2) -> Optional[PathFit]:
    """Factor on the distance from the cameras of the tracked object that makes the path of one of
    its points the polynomial of ``degree`` closest to that point's lines of sight.

    The point is the one whose path fits best: a grid of points within POINT_REACH object sizes
    (``size``, world units) of the track's centre when the track turns (``turns``; the centre of a
    spinning ball, the hinge of a swinging arm), else the centre. None with fewer than
    MIN_PATH_LATENTS latents where the track saw its object, a fit conditioned under MIN_CONDITION
    (the cameras' path does not decide the depth) or no positive distance."""
    return path_fits(track, size, eyes, times, turns, (degree,))[degree]


def path_fits(track: RigidTrack, size: float, eyes: Float[Tensor, "N 3"], times: Float[Tensor, "N"], turns: bool,
              degrees: Tuple[int, ...]) -> Dict[int, Optional[PathFit]]:
    """``path_depth`` for each of ``degrees``, the body points' lines of sight built once."""
    fits: Dict[int, Optional[PathFit]] = {degree: None for degree in degrees}
    seen = track.seen().to(eyes.device)
    if int(seen.sum()) < MIN_PATH_LATENTS or size <= 0:
        return fits
    offsets = torch.zeros(1, 3, dtype=eyes.dtype, device=eyes.device)
    if turns:
        steps = torch.linspace(-POINT_REACH, POINT_REACH, POINT_STEPS, dtype=eyes.dtype, device=eyes.device) * size
        offsets = torch.cartesian_prod(steps, steps, steps)
    points = track.centre + offsets  # [P, 3] canonical
    rotations = rotation_matrices(track.rotvecs[seen])
    paths = rigid_apply(points, track.centre, rotations, track.translations[seen]).transpose(0, 1)  # [P, n, 3]
    rays = paths - eyes[seen]
    lengths = rays.norm(dim=-1).clamp_min(1e-12)  # [P, n] tracked distances
    for degree in degrees:
        distance, residual, condition = triangulate_path(eyes[seen], rays, times[seen].to(eyes.dtype), degree)
        if condition < MIN_CONDITION:
            continue
        factor = (distance / lengths).median(dim=1).values
        relative = residual / (factor.clamp_min(1e-12) * size)  # in sizes of the object at the fitted depth
        relative = torch.where(factor > 0, relative, torch.full_like(relative, float("inf")))
        best = int(torch.argmin(relative))
        if bool(torch.isfinite(relative[best])):
            ratios = torch.full(seen.shape, float("nan"), dtype=eyes.dtype, device=eyes.device)
            ratios[seen] = (distance[best] / lengths[best]).to(eyes.dtype)
            fits[degree] = PathFit(float(factor[best]), float(relative[best]), points[best], ratios, degree)
    return fits


def simplest_path(track: RigidTrack, size: float, eyes: Float[Tensor, "N 3"], times: Float[Tensor, "N"], turns: bool,
                  line_ratio: float, max_residual: float) -> Optional[PathFit]:
    """The quadratic path's depth (``path_depth``), or the straight path's when that passes the
    lines of sight within ``line_ratio`` times the quadratic's residual (and within
    ``max_residual`` object sizes wherever the quadratic does). The quadratic's three extra
    coefficients bend its path to follow the tracked centre's noise, and a noisy track pulls its
    depth in towards the cameras (a path near them passes close to every ray); a mover whose path
    is no straighter than that (a circle, a throw) still gets the quadratic. ``line_ratio`` 0:
    the quadratic only."""
    fits = path_fits(track, size, eyes, times, turns, (2,) if line_ratio <= 0 else (2, 1))
    quad, line = fits[2], fits.get(1)
    if quad is None or line is None or line.residual > line_ratio * quad.residual:
        return quad
    return line if line.residual <= max_residual or quad.residual > max_residual else quad


def clamped_factor(fit: PathFit, limits: Tuple[float, float]) -> float:
    """The fit's factor within ``limits`` (low, high): a guard against runaway fits. Not 1 on the
    high side: the static render behind a mover holds the mover's own smear from the static phase,
    nearer than the background, so the depth it was seeded at is no bound on how far it is."""
    return min(max(fit.factor, limits[0]), limits[1])


def latent_factors(fit: PathFit, limits: Tuple[float, float], follow: float,
                   times: Float[Tensor, "N"]) -> Float[Tensor, "N"]:
    """Factor on every latent's distance: the fit's (``clamped_factor``) on a curved path; on a
    straight one each latent's moved ``follow`` of the way (geometrically) onto the path's own
    distance, within ``limits`` (a latent where the track did not see the object takes the
    factor of the nearest one in time that it did)."""
    base = clamped_factor(fit, limits)
    factors = torch.full(fit.ratios.shape, base, dtype=fit.ratios.dtype, device=fit.ratios.device)
    good = torch.isfinite(fit.ratios) & (fit.ratios > 0)
    if fit.degree != 1 or follow <= 0 or not bool(good.any()):
        return factors
    factors[good] = (base * (fit.ratios[good] / fit.factor) ** follow).clamp(*limits)
    stamps = times.to(fit.ratios.device, fit.ratios.dtype)
    nearest = (stamps[:, None] - stamps[good][None, :]).abs().argmin(dim=1)  # [N] into the good latents
    return torch.where(good, factors, factors[good][nearest])


def rescale(track: RigidTrack, seeds: Seeds, eyes: Float[Tensor, "N 3"], ref: int,
            factor: Union[float, Float[Tensor, "N"]]) -> Tuple[RigidTrack, Seeds]:
    """The track and its seeds ``factor`` (one, or one per latent) times as far from the cameras:
    the seeds and the centre about the reference latent's camera by its factor, every latent's
    position about its own camera by its own, the seeds' radii scaled alike (every latent's view
    of the object unchanged). Rotations stay as they are."""
    factors = torch.as_tensor(factor, dtype=eyes.dtype, device=eyes.device).expand(eyes.shape[0])
    origin, at_ref = eyes[ref], float(factors[ref])
    centre = origin + at_ref * (track.centre - origin)
    positions = eyes + factors[:, None] * (track.centre + track.translations - eyes)
    scaled = replace(track, centre=centre, translations=positions - centre)
    points = origin + at_ref * (seeds.points - origin)
    return scaled, Seeds(points, seeds.colors, seeds.radii * at_ref, centre)

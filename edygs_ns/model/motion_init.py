"""Motion initialisation at the static -> dynamic switch: find the moving objects, seed and track each.

Input: the static model's render of every training latent (colour, depth) and the latents
themselves. Output (``MotionInit``): dynamic seeds, one rigid body per moving object for the
deformation's base motion (``deformation.RigidMotion``), and the mask-consistency targets M̂.

1. **Motion evidence** (``dynamic_seeding.motion_evidence``): where the static render cannot
   explain a latent.
2. **Objects**: the connected evidence regions of the reference latent (the one nearest
   ``reference_time``), largest first, then, while any latent still holds a large evidence region
   that no object found so far covers, the largest of those, with its own latent as reference (an
   object missed or unseen at the reference time). Regions smaller than ``min_object_fraction`` of
   the image, or than ``min_relative_size`` of the first (largest) region, are noise: every
   tracked region costs a full track at the switch. A region that narrows to a neck (under twice
   ``neck_fraction`` of its radius) is cut there (``split_at_necks``: two objects touching in that
   latent, or an object beside a flaw of the static model); its parts are tracked apart, and kept
   apart when their tracks part by more than ``part_divergence`` times their summed sizes
   (``parts_diverge``), else the whole region is tracked as one. Two objects that overlap in that
   latent (crossing there) show no neck; once every region is judged, a mover whose claimed zone,
   outside the other movers' footprints, holds two or more evidence parts in ``apart_presence`` of
   the latents is tracked again as those parts from the latent where they are most even
   (``apart_latent``), and replaced by them when their tracks part as above.
3. Each object gets its own seeds (a cap at its own median static depth), its own rigid track
   (``rigid_track.track_rigid``, which follows only the evidence near the object), then seeds and
   track together move to the depth at which the path of one of its points is a quadratic in
   time, or a straight line where that fits about as well (``path_depth.simplest_path``: the
   training views cannot tell the depth of an independent mover; on a straight line each latent
   goes part of the way onto the line's own distance, ``path_depth.latent_factors``), its
   coverage seeds and its own reach. A region is a mover only if its track holds: its evidence is found in
   at least ``min_presence`` of the latents and the tracked silhouette overlaps it (mean IoU at
   least ``min_object_iou``; scattered residual noise does neither), and no static point explains
   the track: wherever on the reference latent's ray through the region a still point is put (the
   static depth may be wrong), the tracked centre strays from it by ``still_shift`` of the region's
   radius (at least ``still_shift_fraction``, at most ``still_shift_cap`` of the image width; only
   ``still_shift_fraction`` when its rigid silhouette held through ``held_presence`` of the
   latents: such a track does not slide about inside loose evidence, and a large object rolls less
   than its size) in some latent, and its evidence lies where the training views see the static scene about as often
   as they see the clip's typical pixel (``min_view_support``, ``view_support``: where few views
   saw it, e.g. past the path's end or at the frame's edge, the static model is poorly fitted and
   its residual is no motion). A region followed
   through ``steady_presence`` of the latents is kept even when the rigid silhouette fits it
   poorly (a deforming or articulated object), if it strays ``steady_shift`` (not ``still_shift``)
   of its radius and its silhouette still overlaps it by ``steady_iou`` (under that the track
   drifted off its evidence, and its shift is drift); its body then moves without turning and the
   deformation MLP's residual carries the rest (the fallback where a rigid fit is poor). Otherwise it is a flaw of the static model. A track that mostly runs
   inside a mover's claimed zone is that mover again (started where it crossed another object;
   parts cut from one region are not tested against each other); in the latent where a mover was
   found, the other separate regions are other objects: they stay unclaimed, and are tested
   against the mover's footprint there, not its zone. A region that is no mover gets
   no seeds and no body: nothing moving, nothing added. An object that only turns in place is not
   told from a flaw (its rotation fit on a few pixels is noise-level evidence).
4. M̂ is the evidence near the kept objects' tracks (the rest of the evidence is no object).

Once more later (``schedule.evidence_refresh_iters`` into the dynamic phase, ``EdygsModel.refresh_motion``):
the same steps on the dynamic model's renders, with the zone of the movers found so far given
as ``covered`` (their evidence is explained, and a track that runs inside it is one of them
again) and only regions that fit a rigid silhouette kept (the leftover residual near an
imperfect mover is present everywhere), so an object the switch missed gets its seeds, rigid
body and M̂ then.

The rigid body is the base of the deformation, not its limit: the MLP's residual (zero at the
switch) carries what a rigid motion cannot (articulated or deforming objects), and the body's own
track keeps training with the photometric losses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Callable, List, Optional, Tuple

import numpy as np
import torch
from jaxtyping import Bool, Float
from scipy import ndimage
from torch import Tensor

from edygs_ns.model.dynamic_seeding import EIGHT_CONNECTED, DynamicSeedingConfig, Seeds, seed_gaussians
from edygs_ns.model.path_depth import PathFit, latent_factors, rescale, simplest_path
from edygs_ns.model.rigid_track import RigidTrack, RigidTrackConfig, coverage_seeds, spread, track_rigid
from edygs_ns.model.view_support import relative_support, typical_support
from edygs_ns.render.contract import RasterBackend


@dataclass
class MotionObject:
    """One tracked evidence region: its reference latent, seeds (tracked ones first, then coverage
    seeds), rigid track, reach (world units), largest image shift (in its radii), whether it moved
    and, when it did not, why (``verdict``, for the log)."""

    ref: int
    seeds: Seeds
    track: RigidTrack
    reach: float
    shift: float
    moved: bool
    verdict: str = ""
    path: Optional[PathFit] = None
    cut: str = ""  # "neck": a part of a region cut at a neck (``split_at_necks``); "apart": of a mover's
    # region tracked again from a latent where it fell apart (``apart_latent``)

    @property
    def size(self) -> float:
        """Mean distance of the seeds from the track's centre, world units (the unit of the shifts)."""
        return float((self.seeds.points - self.track.centre).norm(dim=-1).mean())

    def _applied(self) -> str:
        factors = None if self.path is None else self.path.applied
        if factors is None:
            return "; not applied"
        low, high = float(factors.min()), float(factors.max())
        return f"; latents x{low:.2f}-{high:.2f}" if high - low >= 0.005 else ""

    def summary(self) -> str:
        turn = float(self.track.rotvecs.norm(dim=-1).max()) * 180.0 / torch.pi
        iou = self.track.iou[torch.isfinite(self.track.iou)] if self.track.iou is not None else torch.zeros(0)
        fit = f", in {len(iou)} latents, silhouette IoU {float(iou.mean()):.2f}" if len(iou) else ", in no latent"
        why = f"; {self.verdict}" if self.verdict and not self.moved else ""
        shape = "straight" if self.path is not None and self.path.degree == 1 else "quadratic"
        depth = "" if self.path is None else (f", path depth x{self.path.factor:.2f} ({shape}, off its lines of sight by "
                                               f"{self.path.residual:.2f} sizes{self._applied()})")
        part = {"neck": " (part of a region cut at a neck)", "apart": " (part of a mover's region, apart in this latent)"}.get(self.cut, "")
        return f"latent {self.ref}{part}: {len(self.seeds.points)} seeds, moves {self.shift:.1f} radii in the image, turns {turn:.0f}°{fit}{depth}{why}"


@dataclass
class MotionInit:
    """What the switch adds: the moving objects (kept and discarded) and M̂ [N, H, W] in {0, 1}."""

    objects: List[MotionObject] = field(default_factory=list)
    consistency: Optional[Tensor] = None

    @property
    def movers(self) -> List[MotionObject]:
        return [o for o in self.objects if o.moved]

    def seed_tensors(self) -> Seeds:
        """Every mover's seeds stacked (centre: unused, zeros)."""
        movers = self.movers
        if not movers:
            empty = torch.zeros(0, 3)
            return Seeds(empty, empty.clone(), torch.zeros(0), torch.zeros(3))
        return Seeds(
            torch.cat([o.seeds.points for o in movers]), torch.cat([o.seeds.colors for o in movers]),
            torch.cat([o.seeds.radii for o in movers]), torch.zeros(3, device=movers[0].seeds.points.device),
        )


def evidence_regions(evidence: Float[Tensor, "H W"], min_pixels: int) -> List[Tensor]:
    """The 8-connected regions of a 0/1 evidence image with at least ``min_pixels`` pixels, largest
    first, each a [H, W] bool mask on the evidence's device."""
    labels, count = ndimage.label(evidence.detach().cpu().numpy() > 0.5, structure=EIGHT_CONNECTED)
    if count == 0:
        return []
    sizes = np.bincount(labels.ravel())[1:]
    order = [int(k) + 1 for k in np.argsort(-sizes, kind="stable") if sizes[k] >= min_pixels]
    labels_t = torch.from_numpy(labels).to(evidence.device)
    return [labels_t == k for k in order]


def split_at_necks(region: Bool[Tensor, "H W"], neck_fraction: float, min_pixels: int, min_share: float = 0.25) -> List[Tensor]:
    """The parts of ``region`` joined only by a neck narrower than twice ``neck_fraction`` of its
    radius (two objects that touch in this latent, or an object and a flaw of the static model
    beside it): the region eroded by a disk of that radius falls apart into cores (each at least a
    tenth of the largest), and every pixel goes to its nearest core. ``[region]`` when it does not
    fall apart or a part would be under ``min_pixels`` or under ``min_share`` of the region."""
    mask = region.detach().cpu().numpy().astype(bool)
    erosion = int(round(neck_fraction * (mask.sum() / np.pi) ** 0.5))
    if erosion < 1:
        return [region]
    offsets = np.arange(-erosion, erosion + 1)
    disk = offsets[:, None] ** 2 + offsets[None, :] ** 2 <= erosion * erosion
    labels, count = ndimage.label(ndimage.binary_erosion(mask, disk), structure=EIGHT_CONNECTED)
    if count < 2:
        return [region]
    sizes = np.bincount(labels.ravel())[1:]
    cores = [k + 1 for k in range(count) if sizes[k] >= 0.1 * sizes.max()]
    if len(cores) < 2:
        return [region]
    labels = np.where(np.isin(labels, cores), labels, 0)
    _, (rows, cols) = ndimage.distance_transform_edt(labels == 0, return_indices=True)
    nearest = labels[rows, cols]
    parts = [mask & (nearest == k) for k in cores]
    if min(int(part.sum()) for part in parts) < max(min_pixels, min_share * mask.sum()):
        return [region]
    return [torch.from_numpy(part).to(region.device) for part in sorted(parts, key=lambda part: -int(part.sum()))]


def parts_diverge(tracks: List[RigidTrack], sizes: List[float], divergence: float) -> bool:
    """Whether the tracks of a region's parts move apart: in some latent two of them have moved
    relative to each other by more than ``divergence`` times their summed sizes (world units)."""
    for a in range(len(tracks)):
        for b in range(a + 1, len(tracks)):
            apart = (tracks[a].translations - tracks[b].translations).norm(dim=-1).max()
            if float(apart) > divergence * (sizes[a] + sizes[b]):
                return True
    return False


def apart_latent(zone: Bool[Tensor, "N H W"], min_pixels: int, min_share: float,
                 min_latents: int) -> Optional[Tuple[int, List[Tensor]]]:
    """Where a mover's evidence falls apart: ``zone`` is the evidence in its claimed zone outside the
    other movers' footprints; a latent is split when it holds two or more regions of at least
    ``min_pixels`` and ``min_share`` of that latent's zone each. With at least ``min_latents`` split
    latents, (the one whose second-largest part is largest, its parts largest first); else None."""
    best: Optional[Tuple[int, List[Tensor]]] = None
    count, balance = 0, 0
    for j in range(zone.shape[0]):
        total = int(zone[j].sum())
        if total < 2 * min_pixels:
            continue
        parts = [r for r in evidence_regions(zone[j].float(), min_pixels) if int(r.sum()) >= min_share * total]
        if len(parts) < 2:
            continue
        count += 1
        if int(parts[1].sum()) > balance:
            best, balance = (j, parts), int(parts[1].sum())
    return best if count >= min_latents else None


def _next_region(evidence: Tensor, covered: Tensor, ref: int, min_pixels: int) -> Optional[tuple]:
    """(latent, region) of the largest uncovered evidence region: the reference latent's first,
    then any latent's; None when none is left."""
    free = (evidence > 0.5) & ~covered
    regions = evidence_regions(free[ref].float(), min_pixels)
    if regions:
        return ref, regions[0]
    best = None
    for i in range(evidence.shape[0]):
        if int(free[i].sum()) < min_pixels:
            continue
        regions = evidence_regions(free[i].float(), min_pixels)
        if regions and (best is None or int(regions[0].sum()) > int(best[1].sum())):
            best = (i, regions[0])
    return best


#: Distances along the reference ray (as multiples of the tracked centre's distance) tried as the
#: depth of a static point that might explain a tracked region.
STATIC_DEPTH_FACTORS = torch.logspace(-0.5, 0.5, 41)


def _project(points: Tensor, viewmats: Tensor, Ks: Tensor) -> Tensor:
    """Pixel positions [N, 2] of one world point [N, 3] per camera (viewmats world-to-camera, OpenCV)."""
    cam = torch.einsum("nij,nj->ni", viewmats[:, :3, :3], points) + viewmats[:, :3, 3]
    pix = torch.einsum("nij,nj->ni", Ks, cam)
    return pix[:, :2] / pix[:, 2:].clamp_min(1e-9)


def unexplained_shift(track: RigidTrack, ref: int, viewmats: Float[Tensor, "N 4 4"], Ks: Float[Tensor, "N 3 3"],
                      cams_to_world_cv: Float[Tensor, "N 4 4"]) -> float:
    """How far (pixels) the tracked centre strays from the best static explanation: a point that
    stands still somewhere on the reference latent's ray through the centre (the static depth it
    was seeded at may be wrong, which alone makes a static flaw seem to move as the camera moves).
    The largest distance over the latents where the track saw the object, minimised over depths."""
    n = viewmats.shape[0]
    seen = track.seen().to(viewmats.device)
    if not bool(seen.any()):
        return 0.0
    tracked = _project(track.centre + track.translations, viewmats, Ks)[seen]
    origin = cams_to_world_cv[ref, :3, 3]
    best = float("inf")
    for factor in STATIC_DEPTH_FACTORS.tolist():
        still = (origin + factor * (track.centre - origin)).expand(n, 3)
        shift = (tracked - _project(still, viewmats, Ks)[seen]).norm(dim=-1).max()
        best = min(best, float(shift))
    return best


def needed_shift(radius_px: float, width: int, seeding: DynamicSeedingConfig, radii: Optional[float] = None,
                 held: bool = False) -> float:
    """The unexplained shift (pixels) that makes a region of radius ``radius_px`` (pixels) a mover:
    ``radii`` (default ``still_shift``) of its radius, at least ``still_shift_fraction`` and at most
    ``still_shift_cap`` of the width; only ``still_shift_fraction`` of the width for a region whose
    rigid silhouette ``held`` through ``held_presence`` of the latents (a track that cannot slide
    about inside loose evidence: a large, slow object)."""
    floor = seeding.still_shift_fraction * width
    if held:
        return floor
    needed = min((seeding.still_shift if radii is None else radii) * radius_px, seeding.still_shift_cap * width)
    return max(needed, floor)


def strays_far(shift_px: float, radius_px: float, width: int, seeding: DynamicSeedingConfig, radii: Optional[float] = None,
               held: bool = False) -> bool:
    """Whether a track's unexplained shift (pixels) makes its region a mover (``needed_shift``)."""
    return shift_px >= needed_shift(radius_px, width, seeding, radii, held)


def verdict(presence: float, mean_iou: float, rigid_fit: bool, steady: bool, shift_px: float, needed_px: float,
            duplicate: bool, seeding: DynamicSeedingConfig, support: float = 1.0) -> str:
    """Why a tracked region is no mover (the first test it fails, in the order of the module
    docstring), or "" when it is one."""
    if presence < seeding.min_presence:
        return f"found in {presence:.0%} of the latents, under {seeding.min_presence:.0%}"
    if not rigid_fit and not (steady and presence >= seeding.steady_presence and mean_iou >= seeding.steady_iou):
        why = f"silhouette IoU {mean_iou:.2f} under {seeding.min_object_iou:.2f}"
        if steady and presence < seeding.steady_presence:
            why += f" and found in {presence:.0%} of the latents, under {seeding.steady_presence:.0%}"
        elif steady:
            why += f", and under {seeding.steady_iou:.2f} for a region found in most latents"
        return why
    if shift_px < needed_px:
        return f"strays {shift_px:.1f} px from a still point, under the {needed_px:.1f} px needed"
    if support < seeding.min_view_support:
        return (f"its evidence lies where few training views see the static scene ({support:.2f} of the "
                f"clip's typical support, under {seeding.min_view_support:.2f})")
    if duplicate:
        return "follows a mover found before"
    return ""


def _duplicate(track: RigidTrack, zones: List[Tensor], share: float = 0.5) -> bool:
    """Whether ``track`` follows a mover already found: in the median latent where it sees its
    object, more than ``share`` of its footprint lies in one of the movers' ``zones`` ([N, H, W]
    bool each: a claimed zone, or the footprint of a mover found in the same latent; two tracks of
    one object, e.g. one started where the object crossed another)."""
    own = track.footprints
    sizes = own.flatten(1).sum(dim=1)
    seen = sizes > 0
    if not bool(seen.any()):
        return False
    for zone in zones:
        inside = (own & zone).flatten(1).sum(dim=1)[seen] / sizes[seen]
        if float(inside.median()) > share:
            return True
    return False


def initialise_motion(
    evidence: Float[Tensor, "N H W"],
    depth: Float[Tensor, "N H W"],
    statics: Float[Tensor, "N H W 3"],
    latent: Callable[[int], Float[Tensor, "H W 3"]],
    viewmats: Float[Tensor, "N 4 4"],
    cams_to_world_cv: Float[Tensor, "N 4 4"],
    Ks: Float[Tensor, "N 3 3"],
    times: Float[Tensor, "N"],
    ref: int,
    backend: RasterBackend,
    seeding: DynamicSeedingConfig,
    tracking: RigidTrackConfig,
    covered: Optional[Tensor] = None,
    existing: int = 0,
    candidates: Optional[int] = None,
    steady: bool = True,
) -> MotionInit:
    """Find, seed and track every moving object (see the module docstring).

    Args:
        evidence: 0/1 motion evidence of every training latent.
        depth: static render's depth (camera z, world units; 0 where nothing was rendered).
        statics: static render of every latent (RGB in [0, 1]); the seeds are tracked over it.
        latent: training image i (RGB in [0, 1]) by index.
        viewmats: world-to-camera (OpenCV axes); cams_to_world_cv: their inverses; Ks: intrinsics.
        times: normalised time of every latent; ref: the reference latent.
        covered: [N, H, W] bool, pixels already explained (the movers found earlier); None: none.
        existing: movers found earlier (they count against ``max_objects``).
        candidates: regions to track at most (default ``max_candidates``).
        steady: keep a region on its presence alone when its rigid fit is poor (``steady_presence``);
            off at the refresh, where the dynamic model's leftover residual is present near every
            imperfect mover and only a region that fits a rigid silhouette is a new object.
    """
    n, height, width = evidence.shape
    min_pixels = max(1, int(round(seeding.min_object_fraction * height * width)))
    earlier = [] if covered is None else [covered.bool()]  # the zone of the movers found before
    covered = torch.zeros_like(evidence, dtype=torch.bool) if covered is None else covered.clone().bool()
    result = MotionInit()
    typical = typical_support(depth, viewmats, cams_to_world_cv, Ks)

    def seeded(k: int, region: Tensor) -> Optional[tuple]:
        """(region, seeds, rigid track) of one evidence region of latent k; None without seeds."""
        seeds = seed_gaussians(region.float(), depth[k], latent(k), Ks[k], cams_to_world_cv[k], seeding)
        if len(seeds.points) == 0:
            return None
        return region, seeds, track_rigid(seeds.points, seeds.colors, seeds.radii, seeds.centre, times, evidence, latent,
                                          statics, viewmats, Ks, k, backend, tracking, seeding)

    def diverging(k: int, parts: List[Tensor]) -> Optional[List[tuple]]:
        """The parts of latent k seeded and tracked, when at least two are and their tracks part
        (``parts_diverge``); else None."""
        tracked = [t for t in (seeded(k, part) for part in parts) if t is not None]
        sizes = [float(spread(seeds.points, seeds.centre)) for _, seeds, _ in tracked]
        apart = len(tracked) > 1 and parts_diverge([track for _, _, track in tracked], sizes, seeding.part_divergence)
        return tracked if apart else None

    def tracked_parts(k: int, region: Tensor, min_pixels: int) -> List[tuple]:
        """The region cut at its necks when the parts' tracks move apart (two objects touching in
        latent k, or an object beside a flaw of the static model), else the whole region."""
        parts = split_at_necks(region, seeding.neck_fraction, min_pixels, seeding.neck_min_share) if seeding.neck_fraction > 0 else [region]
        tracked = diverging(k, parts) if len(parts) > 1 else None
        if tracked is not None:
            return tracked
        whole = seeded(k, region)
        return [] if whole is None else [whole]

    def judge(k: int, region: Tensor, seeds: Seeds, track: RigidTrack, found_before: List[MotionObject]) -> MotionObject:
        """The tracked region's depth, coverage seeds, reach and verdict (mover or not, and why); a
        duplicate is told against the movers of ``found_before`` (not against parts of its own region)."""
        iou = track.iou[track.seen()]
        rigid_fit = len(iou) > 0 and float(iou.mean()) >= seeding.min_object_iou
        path = None
        if seeding.path_depth:
            path = simplest_path(track, float(spread(seeds.points, seeds.centre)), cams_to_world_cv[:, :3, 3], times,
                                 rigid_fit, seeding.path_depth_line_ratio, seeding.path_depth_max_residual)
        if path is not None and path.residual <= seeding.path_depth_max_residual:
            path.applied = latent_factors(path, seeding.path_depth_range, seeding.path_depth_follow, times)
            track, seeds = rescale(track, seeds, cams_to_world_cv[:, :3, 3], k, path.applied)
        own = evidence * track.footprints
        extra = coverage_seeds(track, seeds.points, seeds.radii, own, depth, latent, Ks, cams_to_world_cv, times, k, seeding)
        points = torch.cat([seeds.points, extra.points])
        every = Seeds(points, torch.cat([seeds.colors, extra.colors]), torch.cat([seeds.radii, extra.radii]), track.centre)
        distances = (points - track.centre).norm(dim=-1)
        radius_px = (float(region.sum()) / torch.pi) ** 0.5
        shift_px = unexplained_shift(track, k, viewmats, Ks, cams_to_world_cv)
        presence = len(iou) / n
        mean_iou = float(iou.mean()) if len(iou) else 0.0
        # a region followed through most of the clip is real even when one rigid silhouette fits it
        # poorly (a deforming or articulated object): its track then only carries it, see below
        held = rigid_fit and presence >= seeding.held_presence  # no track sliding inside loose evidence
        needed_px = needed_shift(radius_px, width, seeding, seeding.still_shift if rigid_fit else seeding.steady_shift, held)
        # a mover found in this same latent is where its footprint is: a separate region beside it
        # there is another object, even inside its claimed zone
        zones = [o.track.footprints if o.ref == k else o.track.claims for o in found_before if o.moved]
        duplicate = _duplicate(track, earlier + zones)
        support = relative_support(track.footprints & (evidence > 0.5), typical, depth, viewmats, cams_to_world_cv, Ks)
        why = verdict(presence, mean_iou, rigid_fit, steady, shift_px, needed_px, duplicate, seeding, support)
        moved = why == ""
        if moved and not rigid_fit:
            # poor rigid fit: keep the track's translation as the base motion, drop its rotation (a
            # turn fitted to a changing shape is noise); the MLP residual carries the rest
            track = replace(track, rotvecs=torch.zeros_like(track.rotvecs))
        return MotionObject(k, every, track, tracking.reach * float(distances.max()), shift_px / max(radius_px, 1e-9),
                            moved, why, path)

    for _ in range(seeding.max_candidates if candidates is None else candidates):
        found = _next_region(evidence, covered, ref, min_pixels)
        if found is None or existing + len(result.movers) >= seeding.max_objects:
            break
        k, region = found
        # each track costs as much as the largest one: once a large region was tracked, much
        # smaller ones (pose-error specks, fragments) are not worth one
        min_pixels = max(min_pixels, int(seeding.min_relative_size * float(region.sum())))
        # the latent's other separate regions stay to be tracked even inside this one's claims
        others = evidence_regions(((evidence[k] > 0.5) & ~covered[k] & ~region).float(), min_pixels)
        others = torch.stack(others).any(dim=0) if others else torch.zeros_like(region)
        covered[k] |= region
        found_before = list(result.objects)
        pieces = tracked_parts(k, region, min_pixels)
        for part, seeds, track in pieces:
            if existing + len(result.movers) >= seeding.max_objects:
                break
            result.objects.append(judge(k, part, seeds, track, found_before))
            result.objects[-1].cut = "neck" if len(pieces) > 1 else ""
            covered |= track.claims
            covered[k] &= ~others
    # a mover whose region joined two objects in its latent (touching or crossing there): where
    # they are apart, the evidence in its zone outside the other movers falls into parts; tracked
    # from the latent where they are most even, parts whose tracks part are objects of their own
    present = evidence > 0.5
    for mover in list(result.movers):
        others = [o for o in result.movers if o is not mover]
        outside = torch.zeros_like(present)
        for zone in [o.track.footprints for o in others] + earlier:
            outside |= zone
        apart = apart_latent(present & mover.track.claims & ~outside, min_pixels, seeding.neck_min_share,
                             int(math.ceil(seeding.apart_presence * n)))
        if apart is None:
            continue
        j, parts = apart
        tracked = diverging(j, parts)
        if tracked is None:
            continue
        judged = [judge(j, part, seeds, track, others) for part, seeds, track in tracked]
        if any(o.moved for o in judged):
            for o in judged:
                o.cut = "apart"
            at = result.objects.index(mover)
            result.objects[at:at + 1] = judged
    movers = result.movers
    if movers:
        near = torch.stack([o.track.claims for o in movers]).any(dim=0)
        result.consistency = evidence * near
    else:
        result.consistency = torch.zeros_like(evidence)
    return result

"""Rigid tracking of one moving object's seeds by photometric alignment (motion initialisation).

The seeds of one moving object are back-projected from one evidence region of one latent
(``motion_init.py``). The object moves *and turns*: the built-in sphere spins half a turn over a
clip, a thrown or rolling object does the same. A translation track of the evidence blob cannot
express that, so the deformation field would have to discover the rotation from the photometric
loss in the few hundred iterations of the dynamic phase, and until it does every seed is the
time-average of the colours that pass through it (a smeared object).

Here the seeds' motion is first estimated as one rigid transform per training latent,

    x_i = R_i (x - c) + c + τ_i,     R_i = exp(ω_i),

about the seeds' centre c. Each (ω_i, τ_i) is fitted by a few Adam steps on the L1 difference
between the latent and the seeds rendered over the static model's render of that latent (the
seeds alone are rasterised, so a step costs a few hundred Gaussians), plus a silhouette term
between the seeds' alpha and the object's motion evidence. The silhouette's seeds are translated
and turned only by the fit's twist about the line of sight: a bar or an arm turning in the view
turns its outline, a ball spinning its seen side away keeps it; the colours alone turn the fit
(``silhouette_twist`` off: translated only). Latents are visited outwards in time
from the object's reference latent, each one starting from its neighbour's transform; in each
latent only the evidence near the object's silhouette at that start counts (another mover's
evidence neither pulls the fit nor enters its loss). The track becomes the object's rigid body
in the deformation (``deformation.RigidMotion``), places extra seeds for the parts the reference
latent did not see (``coverage_seeds``), and its footprints say which evidence is this object's.

Keyframes: the seeds are the side the reference latent saw, and an object that turns far enough
turns them out of view, leaving the colour fit nothing to follow (the sphere's track lagged by
30-60 degrees at the clip's ends). So each time a pass's fit has turned ``keyframe_turn`` degrees
since its last keyframe, that latent's evidence adds seeds where none is yet (a cap at the tracked
centre's depth, taken to the canonical frame by the latent's inverse transform); the colour fit
renders them, the silhouette stays the reference seeds' (the outline, the footprints and the mover
test are as without them), and each pass (later, then earlier latents) keeps only its own. A
keyframe is taken only where the outline turned by the fit still fits the object's evidence, and
seeds only inside that outline: a squashing body's "turn" is its outline changing shape, and a
hinged neighbour's evidence lies within the follow zone; neither is a side that turned into view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Tuple

import torch
from jaxtyping import Float
from nerfstudio.cameras.lie_groups import exp_map_SO3xR3
from torch import Tensor
from tyro.conf import Suppress

from edygs_ns.geometry import camera_centres, rotation_angle
from edygs_ns.model.dynamic_seeding import DynamicSeedingConfig, Seeds, dilate, seed_gaussians
from edygs_ns.render.contract import RasterBackend


@dataclass
class RigidTrackConfig:
    """Photometric rigid tracking of the dynamic seeds (part of the motion initialisation). Fields
    marked ``Suppress`` are hidden from ``ns-train --help`` and the command line (docs/method.md,
    "Configuration notes")."""

    enabled: bool = True
    """track each object's seeds as a rigid body (off: one translation track)"""
    steps: int = 25
    """Adam steps per latent"""
    lr_rotation: Suppress[float] = 0.02
    """Adam learning rate of the rotation vector ω (radians)"""
    lr_translation: Suppress[float] = 0.02
    """Adam learning rate of the translation τ in units of the seeds' radius"""
    as_base_motion: bool = True
    """the tracks are the deformation's base motion (off: the MLP learns them)"""
    reach: Suppress[float] = 1.25
    """a body moves deformed Gaussians within this many times its seeds' largest radius"""
    opacity: Suppress[float] = 0.95
    """opacity of the seeds while tracking"""
    region_dilation: Suppress[float] = 0.04
    """the fit counts pixels within this fraction of the image width of the object's evidence"""
    follow_margin: Suppress[float] = 1.0
    """evidence within this many object radii of its silhouette is its own"""
    silhouette_weight: float = 0.2
    """weight of the silhouette term beside the colour L1 of the fit"""
    silhouette_twist: bool = True
    """the silhouette's seeds turn with the fit about the line of sight (off: translated only)"""
    extrapolate: bool = False
    """start each latent's fit at the last two fits' constant velocity (not kept)"""
    keyframe_turn: float = 30.0
    """once the fit has turned this many degrees since the last seeding, the latent's evidence adds
    seeds to the fitted set (the side that turned into view keeps colour to fit); 0: off"""
    keyframe_outline: Suppress[bool] = True
    """a keyframe only where the turned outline still fits the object's evidence (IoU at least the
    mover test's ``min_object_iou``), seeded inside that outline (off: the whole followed evidence)"""


#: A window (y0, y1, x0, x1) of an image: rows y0..y1-1, columns x0..x1-1.
Window = Tuple[int, int, int, int]


@dataclass
class RigidTrack:
    """Per-latent rigid transforms of the seeds: rotation vectors [N, 3] (radians), translations
    [N, 3] (world units), about the centre [3]; ``loss`` [N] is the final fit loss (mean absolute
    colour error near the motion evidence, plus the weighted silhouette error); ``footprints``
    [N, H, W] bool the pixels near the tracked seeds in every latent, ``claims`` the wider zone
    within the follow margin (evidence there is this object's, not another's); ``iou`` [N] the intersection
    over union of the tracked seeds' silhouette, translated only, with the object's evidence (NaN
    where the latent has none): the mover test reads it, and a turn fitted to noise must not raise it.
    ``keyframes`` maps each latent that added seeds to the colour fit to those seeds [K, 3]
    (canonical frame, world units)."""

    centre: Tensor
    rotvecs: Tensor
    translations: Tensor
    loss: Tensor
    footprints: Optional[Tensor] = None
    claims: Optional[Tensor] = None
    iou: Optional[Tensor] = None
    keyframes: Dict[int, Tensor] = field(default_factory=dict)

    def rotations(self) -> Float[Tensor, "N 3 3"]:
        return rotation_matrices(self.rotvecs)

    def seen(self) -> Tensor:
        """[N] bool: the latents where the track saw its object (every latent without ``iou``)."""
        if self.iou is None:
            return torch.ones(len(self.rotvecs), dtype=torch.bool, device=self.rotvecs.device)
        return torch.isfinite(self.iou)

    def apply(self, points: Float[Tensor, "S 3"]) -> Float[Tensor, "N S 3"]:
        """Positions of canonical points at every latent."""
        return rigid_apply(points, self.centre, self.rotations(), self.translations)

    def to_canonical(self, points: Float[Tensor, "S 3"], index: int) -> Float[Tensor, "S 3"]:
        """Canonical positions of points observed at latent ``index`` (the inverse transform)."""
        rotation = self.rotations()[index]
        return (points - self.centre - self.translations[index]) @ rotation + self.centre


def rotation_matrices(rotvecs: Float[Tensor, "N 3"]) -> Float[Tensor, "N 3 3"]:
    """Rotation matrices of axis-angle vectors (nerfstudio's SO(3) exponential map)."""
    tangent = torch.cat([torch.zeros_like(rotvecs), rotvecs], dim=-1)
    return exp_map_SO3xR3(tangent)[:, :3, :3]


def twist_about(rotvec: Float[Tensor, "3"], axis: Float[Tensor, "3"]) -> Float[Tensor, "3"]:
    """The twist of rotation ``rotvec`` (axis-angle, radians) about ``axis`` (any length): the part
    of the turn about that axis in the swing-twist decomposition, as a rotation vector."""
    axis = axis / axis.norm().clamp_min(1e-12)
    angle = (rotvec.square().sum() + 1e-24).sqrt()
    along = torch.sin(angle / 2) / angle * (rotvec @ axis)  # the quaternion's vector part along the axis
    return axis * 2.0 * torch.atan2(along, torch.cos(angle / 2))


def spread(points: Float[Tensor, "S 3"], centre: Float[Tensor, "3"]) -> Tensor:
    """RMS distance of ``points`` from ``centre`` (world units, a 0-d tensor): an object's size."""
    return (points - centre).norm(dim=-1).square().mean().sqrt()


def rigid_apply(points: Tensor, centre: Tensor, rotations: Tensor, translations: Tensor) -> Tensor:
    """R (x - c) + c + τ for [S, 3] points and [N, 3, 3] rotations / [N, 3] translations -> [N, S, 3]."""
    local = points - centre
    return torch.einsum("nij,sj->nsi", rotations, local) + centre + translations[:, None]


def visiting_order(times: Float[Tensor, "N"], ref: int) -> List[Tuple[int, int]]:
    """(latent, neighbour) index pairs outwards in time from latent ``ref``: later latents first,
    then earlier ones; the neighbour is the latent one step closer in time to ``ref``."""
    by_time = torch.argsort(times.detach().cpu(), stable=True).tolist()
    start = by_time.index(ref)
    order = []
    for direction in (1, -1):
        k = start + direction
        while 0 <= k < len(by_time):
            order.append((by_time[k], by_time[k - direction]))
            k += direction
    return order


def track_rigid(
    points: Float[Tensor, "S 3"],
    colors: Float[Tensor, "S 3"],
    radii: Float[Tensor, "S"],
    centre: Float[Tensor, "3"],
    times: Float[Tensor, "N"],
    evidence: Float[Tensor, "N H W"],
    latent: Callable[[int], Float[Tensor, "H W 3"]],
    backgrounds: Float[Tensor, "N H W 3"],
    viewmats: Float[Tensor, "N 4 4"],
    Ks: Float[Tensor, "N 3 3"],
    ref: int,
    backend: RasterBackend,
    config: RigidTrackConfig,
    seeding: Optional[DynamicSeedingConfig] = None,
) -> RigidTrack:
    """Fit a rigid transform of the seeds to every latent (identity at ``ref``).

    Args:
        points, colors, radii: the seeds (world units, RGB in [0, 1], isotropic radii).
        centre: the centre of rotation (world units), e.g. the centre of the seeds' blob.
        times: time of every latent (the visiting order).
        evidence: 0/1 motion evidence of every latent; the loss counts pixels near it.
        latent: training image i (RGB in [0, 1]) by index.
        backgrounds: the static model's render of every latent (the seeds are composited over it).
        viewmats: world-to-camera (OpenCV axes) of every latent; Ks: pinhole intrinsics in pixels.
        ref: the latent the seeds were back-projected from.
        seeding: the seeds' shape and spacing for the keyframe seeds (``keyframe_turn``); None: none.
    """
    n = backgrounds.shape[0]
    device = points.device
    eyes = camera_centres(viewmats)  # [N, 3] world: the lines of sight of the outline's twist
    size = spread(points, centre).clamp_min(1e-6)
    rotvecs = torch.zeros(n, 3, device=device)
    units = torch.zeros(n, 3, device=device)  # translation / size
    losses = torch.zeros(n, device=device)

    def splats(radii_: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
        """Identity quaternions, isotropic scales and the tracking opacity of seeds of ``radii_``."""
        quats_ = torch.zeros(len(radii_), 4, device=device)
        quats_[:, 0] = 1.0
        return quats_, radii_[:, None].expand(-1, 3).contiguous(), torch.full((len(radii_),), config.opacity, device=device)

    # the silhouette is the reference seeds' (the outline the reference latent saw); the colour fit
    # renders them plus the keyframe seeds (``keyframe_turn``)
    outline_splats = splats(radii)
    fit = {"points": points, "colors": colors, "radii": radii, "splats": outline_splats}
    height, width = backgrounds.shape[1:3]
    dilation = max(1, int(round(config.region_dilation * width)))
    evidence = evidence.float()
    outlines = torch.zeros_like(evidence)  # this object's evidence, filled per latent
    regions = torch.zeros_like(evidence, dtype=torch.bool)

    def rasterize(i: int, means: Tensor, features: Tensor, win: Optional[Window] = None, fitted: bool = False):
        """The seeds at ``means`` seen from latent i: the whole image, or only the window
        (y0, y1, x0, x1) of it (the principal point shifted; the same pixels, far fewer of them).
        ``fitted``: the colour fit's seeds (else the reference seeds)."""
        quats, scales, opacities = fit["splats"] if fitted else outline_splats
        if win is None:
            return backend(means, quats, scales, opacities, features, viewmats[i : i + 1], Ks[i : i + 1], width, height)
        y0, y1, x0, x1 = win
        K = Ks[i : i + 1].clone()
        K[:, 0, 2] -= x0
        K[:, 1, 2] -= y0
        return backend(means, quats, scales, opacities, features, viewmats[i : i + 1], K, x1 - x0, y1 - y0)

    def silhouette(i: int, turn: Optional[Tensor], unit: Tensor, win: Optional[Window] = None) -> Tensor:
        """[H, W] (or window) alpha of the seeds at latent i turned by ``turn`` (a rotation vector;
        None: translated only) and moved by ``unit``."""
        if turn is None:
            moved = points + (unit * size)[None]
        else:
            moved = rigid_apply(points, centre, rotation_matrices(turn[None]), (unit * size)[None])[0]
        # only alpha is read, so one feature channel is composited
        return rasterize(i, moved, colors[:, :1], win).alpha[0, ..., 0]

    def outline_turn(i: int, rotvec: Tensor) -> Optional[Tensor]:
        """The turn of the object's outline at latent i: the fit's twist about the line of sight
        through the centre (None when ``silhouette_twist`` is off). The seeds are the side the
        reference latent saw: a turn out of the view carries them off the object's outline, a turn
        within it turns the outline."""
        return twist_about(rotvec, centre - eyes[i]) if config.silhouette_twist else None

    def window(i: int) -> Window:
        """The box around latent i's loss region (the only pixels the fit reads), 2 px of margin."""
        rows = torch.nonzero(regions[i].any(dim=1)).squeeze(-1)
        cols = torch.nonzero(regions[i].any(dim=0)).squeeze(-1)
        return (max(int(rows[0]) - 2, 0), min(int(rows[-1]) + 3, height), max(int(cols[0]) - 2, 0), min(int(cols[-1]) + 3, width))

    with torch.no_grad():
        area = float((silhouette(ref, rotvecs[ref], units[ref]) > 0.5).sum())
    follow = dilation + int(round(config.follow_margin * (area / torch.pi) ** 0.5))

    def focus(i: int, rotvec: Tensor, unit: Tensor) -> None:
        """This object's evidence in latent i: near its silhouette at the start transform."""
        with torch.no_grad():
            near = dilate(silhouette(i, rotvec, unit) > 0.5, follow)
        outlines[i] = evidence[i] * near
        regions[i] = dilate(outlines[i] > 0.5, dilation)

    def render_loss(i: int, rotvec: Tensor, unit: Tensor, target: Tensor, win: Window) -> Tensor:
        """Fit loss of latent i (RGB ``target`` [H, W, 3]) for the transform (rotvec, unit),
        rendered only in ``win``, the window around its loss region (``window(i)``)."""
        y0, y1, x0, x1 = win
        region, outline = regions[i, y0:y1, x0:x1], outlines[i, y0:y1, x0:x1]
        moved = rigid_apply(fit["points"], centre, rotation_matrices(rotvec[None]), (unit * size)[None])[0]
        out = rasterize(i, moved, fit["colors"], win, fitted=True)
        composite = out.render[0] + (1.0 - out.alpha[0]) * backgrounds[i, y0:y1, x0:x1]
        loss = (composite - target[y0:y1, x0:x1]).abs()[region].mean()
        if config.silhouette_weight > 0:
            # the outline places the seeds; the colours alone turn them (no gradient into the twist)
            alpha = silhouette(i, outline_turn(i, rotvec.detach()), unit, win=win)
            loss = loss + config.silhouette_weight * (alpha - outline)[region].abs().mean()
        return loss

    def add_keyframe(i: int) -> None:
        """Seeds for latent i's evidence of this object that no fitted seed covers: a cap at the
        tracked centre's depth, taken to the canonical frame by latent i's inverse transform. With
        ``keyframe_outline``: only where the turned outline fits the evidence, and only inside it."""
        cam_to_world = torch.linalg.inv(viewmats[i])
        moved_centre = centre + units[i] * size
        z_centre = float(viewmats[i][2, :3] @ moved_centre + viewmats[i][2, 3])
        if z_centre <= 0:
            return
        own = outlines[i]
        if config.keyframe_outline:
            # a squashing or hinged body's fitted turn can be its outline changing shape, and the
            # follow zone holds a hinged neighbour's evidence: neither is the side that turned in
            shape = silhouette(i, outline_turn(i, rotvecs[i]), units[i]) > 0.5
            present = own > 0.5
            overlap, union = float((shape & present).sum()), float((shape | present).sum())
            if overlap < seeding.min_object_iou * max(union, 1.0):
                return
            own = own * dilate(shape, dilation)
        seen = seed_gaussians(own, torch.ones_like(own), latent(i), Ks[i], cam_to_world, seeding, centre_depth=z_centre)
        if len(seen.points) == 0:
            return
        rotation = rotation_matrices(rotvecs[i][None])[0]
        canonical = (seen.points - centre - units[i] * size) @ rotation + centre
        gap = torch.cdist(canonical, fit["points"]).min(dim=1).values
        new = gap > seeding.coverage_spacing * seen.radii
        if bool(new.any()):
            fit["points"] = torch.cat([fit["points"], canonical[new]])
            fit["colors"] = torch.cat([fit["colors"], seen.colors[new]])
            fit["radii"] = torch.cat([fit["radii"], seen.radii[new]])
            fit["splats"] = splats(fit["radii"])
            added[i] = canonical[new]

    take_keyframes = seeding is not None and config.keyframe_turn > 0
    added: Dict[int, Tensor] = {}  # latent -> the keyframe seeds it added (canonical)
    key_turn = {ref: torch.zeros(3, device=device)}  # latent -> the turn at its pass's last keyframe
    focus(ref, rotvecs[ref], units[ref])
    before: dict = {}  # latent -> the neighbour it was started from
    with torch.enable_grad():
        for i, prev in visiting_order(times, ref):
            before[i] = prev
            if prev == ref:  # each pass (later, then earlier latents) keeps only its own keyframes
                fit.update(points=points, colors=colors, radii=radii, splats=outline_splats)
            key_turn[i] = key_turn[prev]  # a latent without evidence keeps its neighbour's keyframe
            focus(i, rotvecs[prev], units[prev])
            if not bool(regions[i].any()):
                rotvecs[i], units[i] = rotvecs[prev], units[prev]
                continue
            rotvec, unit = rotvecs[prev].clone(), units[prev].clone()
            if config.extrapolate and prev in before:
                pp = before[prev]
                step_prev = float(times[prev] - times[pp])
                scale = float(times[i] - times[prev]) / step_prev if step_prev != 0.0 else 0.0
                rotvec = rotvec + scale * (rotvecs[prev] - rotvecs[pp])
                unit = unit + scale * (units[prev] - units[pp])
            rotvec.requires_grad_(True)
            unit.requires_grad_(True)
            optimizer = torch.optim.Adam(
                [{"params": [rotvec], "lr": config.lr_rotation}, {"params": [unit], "lr": config.lr_translation}]
            )
            target, win = latent(i), window(i)  # once per latent, not per step (window reads the host)
            for _ in range(config.steps):
                loss = render_loss(i, rotvec, unit, target, win)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
            rotvecs[i], units[i] = rotvec.detach(), unit.detach()
            if take_keyframes:
                relative = rotation_matrices(torch.stack([rotvecs[i], key_turn[i]]))
                turned = math.degrees(float(rotation_angle((relative[0] @ relative[1].T).cpu().numpy())))
                if turned > config.keyframe_turn:
                    with torch.no_grad():
                        add_keyframe(i)
                    key_turn[i] = rotvecs[i]
    footprints = torch.zeros_like(regions)
    claims = torch.zeros_like(regions)
    iou = torch.full((n,), float("nan"), device=device)
    with torch.no_grad():
        for i in range(n):
            losses[i] = render_loss(i, rotvecs[i], units[i], latent(i), window(i)) if bool(regions[i].any()) else 0.0
            turn = outline_turn(i, rotvecs[i])
            shape = silhouette(i, turn, units[i]) > 0.5
            footprints[i] = dilate(shape, dilation)
            claims[i] = dilate(shape, follow)
            own = outlines[i] > 0.5
            if bool(own.any()):
                still = shape if turn is None else silhouette(i, None, units[i]) > 0.5
                iou[i] = (still & own).sum() / (still | own).sum()
    return RigidTrack(centre=centre, rotvecs=rotvecs, translations=units * size, loss=losses, footprints=footprints, claims=claims, iou=iou,
                      keyframes=added)


def coverage_seeds(
    track: RigidTrack,
    points: Float[Tensor, "S 3"],
    radii: Float[Tensor, "S"],
    evidence: Float[Tensor, "N H W"],
    depth: Float[Tensor, "N H W"],
    latent: Callable[[int], Float[Tensor, "H W 3"]],
    Ks: Float[Tensor, "N 3 3"],
    cams_to_world_cv: Float[Tensor, "N 4 4"],
    times: Float[Tensor, "N"],
    ref: int,
    config: DynamicSeedingConfig,
) -> Seeds:
    """Canonical seeds for what the reference latent did not see.

    For each of ``config.coverage_times`` the nearest latent's evidence pixels are back-projected
    (a cap centred at the tracked blob centre's depth in that camera), taken back to the canonical
    frame by the inverse rigid transform, and kept where they are farther than
    ``config.coverage_spacing`` radii from every seed so far (the part of the object that turned
    into view). Returns the new seeds only (``centre``: the track's centre)."""
    kept_points, kept_colors, kept_radii = [points.new_zeros(0, 3)], [points.new_zeros(0, 3)], [points.new_zeros(0)]
    every = points
    for t in config.coverage_times:
        k = int(torch.argmin((times - t).abs()))
        if k == ref:
            continue
        centre_k = track.centre + track.translations[k]
        world_to_cam = torch.linalg.inv(cams_to_world_cv[k])
        z_centre = float(world_to_cam[2, :3] @ centre_k + world_to_cam[2, 3])
        if z_centre <= 0:
            continue
        seen = seed_gaussians(evidence[k], depth[k], latent(k), Ks[k], cams_to_world_cv[k], config, centre_depth=z_centre)
        if len(seen.points) == 0:
            continue
        canonical = track.to_canonical(seen.points, k)
        gap = torch.cdist(canonical, every).min(dim=1).values
        new = gap > config.coverage_spacing * seen.radii
        kept_points.append(canonical[new])
        kept_colors.append(seen.colors[new])
        kept_radii.append(seen.radii[new])
        every = torch.cat([every, canonical[new]])
    return Seeds(torch.cat(kept_points), torch.cat(kept_colors), torch.cat(kept_radii), track.centre)

"""Motion evidence and dynamic seeds, the building blocks of the motion initialisation.

At the end of the static phase the static Gaussians explain every latent except where the scene
moved. ``model/motion_init.py`` turns that into moving objects with these pieces:

- ``motion_evidence``: per training latent, the static render's colour residual against the EDI
  latent, box-filtered (a moving object is a blob, pose-error residuals are thin edges) and
  thresholded at a robust level over the whole clip, ``median + threshold_mads · 1.4826 · MAD``, and
  grown into the connected pixels over a lower level (``grow_mads``; hysteresis), taken on the
  background alone when a large mover skews the clip's statistics.
- ``seed_gaussians``: a moving object has no Gaussian of its own after the static phase (a static
  Gaussian on its path sees it only in a few latents, so the mask regulariser keeps such Gaussians
  static). One evidence region of one latent is back-projected a little in front of the static
  depth (a round cap at the region's median depth) into new Gaussians with the EDI colour and a
  high motion mask.
- ``evidence_track`` + ``fit_motion``: without rigid tracking (``--pipeline.model.rigid-track.enabled
  False``), the evidence centroid of every latent back-projected at its static depth gives a
  translation track, and the deformation field is first regressed onto it for the seeds (a few
  hundred MLP-only steps, no rendering), so the photometric losses refine a motion that already
  overlaps the object.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Literal, NamedTuple, Optional, Tuple

import numpy as np
import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float
from scipy import ndimage
from torch import Tensor
from tyro.conf import Suppress

#: MAD -> standard deviation of a normal distribution.
MAD_TO_SIGMA = 1.4826
#: offset of a pixel centre from its corner.
PIXEL_CENTRE = 0.5
#: 8-connected neighbourhood of evidence regions.
EIGHT_CONNECTED = np.ones((3, 3), dtype=bool)
#: Box filter (px) of the fine residual that trims grown evidence, and the gap (px) closed in it.
FINE_WINDOW = 3
CLOSING_STEPS = 2


@dataclass
class DynamicSeedingConfig:
    """Motion evidence and dynamic seeds at the start of the dynamic phase. Fields marked
    ``Suppress`` are the evidence detector's and the seeder's tuning: hidden from ``ns-train --help``
    and the command line, set in Python or a saved config.yml (docs/method.md, "Configuration notes")."""

    enabled: bool = True
    """find moving objects and seed dynamic Gaussians at the dynamic switch"""
    window_fraction: Suppress[float] = 0.055
    """box-filter width of the residual, a fraction of the image width (odd, >= 3 px)"""
    threshold_mads: Suppress[float] = 4.5
    """evidence where the filtered residual exceeds median + this · σ_MAD over all latents"""
    min_threshold: Suppress[float] = 0.03
    """the evidence threshold is at least this (mean absolute colour error in [0, 1])"""
    grow_mads: float = 2.5
    """evidence grows into connected pixels over median + this · σ_MAD"""
    trim_mads: Suppress[float] = 2.5
    """... where the 3 px filtered residual is over its median + this · σ_MAD"""
    background_mads: Suppress[float] = 3.0
    """the background's level: median and σ_MAD again over the values under median + this · σ, ..."""
    background_rounds: Suppress[int] = 5
    """... this many rounds"""
    background_sigma_ratio: Suppress[float] = 0.7
    """grow/trim levels from the background when its σ is under this share of the clip's (a mover big enough to skew it)"""
    reference_time: Suppress[float] = 0.5
    """time of the reference latent, searched first (and the centre of the dynamic time window)"""
    pixel_stride: Suppress[int] = 1
    """seed every this-many-th evidence pixel in each direction"""
    max_seeds: Suppress[int] = 4000
    """at most this many seeds (evenly subsampled)"""
    depth_scale: Suppress[float] = 0.9
    """seeds sit at this fraction of the static render's depth"""
    path_depth: bool = True
    """then move each tracked object to the depth where its path is simplest in time (model/path_depth.py)"""
    path_depth_range: Suppress[Tuple[float, float]] = (0.25, 2.0)
    """... by a factor on its distance clamped to this range (a guard against runaway fits)"""
    path_depth_max_residual: Suppress[float] = 0.3
    """... if the fitted path passes within this many object sizes (RMS) of its lines of sight"""
    path_depth_line_ratio: Suppress[float] = 1.5
    """... a straight path instead when it passes within this times the quadratic's residual (0: quadratic only)"""
    path_depth_follow: Suppress[float] = 0.5
    """on a straight path, each latent's distance moved this share (geometric) onto the path's own (0: one factor)"""
    seed_shape: Suppress[Literal["cap", "flat"]] = "cap"
    """cap: a round cap towards the camera at the region's median depth; flat: per-pixel depth"""
    coverage_times: Suppress[Tuple[float, ...]] = (0.0, 1.0)
    """times of latents whose evidence, carried back by the rigid track, adds seeds (empty: none)"""
    coverage_spacing: Suppress[float] = 1.5
    """a coverage seed is kept only if farther than this many seed radii from every seed"""
    seed_opacity: Suppress[float] = 0.5
    """opacity of a seed"""
    seed_mask: Suppress[float] = 0.9
    """motion mask m of a seed"""
    scale_pixels: Suppress[float] = 0.8
    """seed radius in pixels at its depth (times pixel_stride)"""
    consistency_target: Literal["evidence", "rendered", "max"] = "evidence"
    """M̂ of the dynamic phase (rendered: the paper's)"""
    init_motion_steps: Suppress[int] = 300
    """MLP-only steps regressing the seeds' deformation onto their track (0: off)"""
    init_motion_lr: Suppress[float] = 1e-3
    """Adam learning rate of the motion initialisation"""
    init_motion_batch: Suppress[int] = 512
    """(seed, time) samples per motion-initialisation step"""
    min_object_fraction: Suppress[float] = 0.002
    """evidence regions below this fraction of the image are noise"""
    min_relative_size: Suppress[float] = 0.1
    """regions below this fraction of the largest tracked region are not tracked"""
    neck_fraction: Suppress[float] = 0.25
    """a region is cut into parts where it narrows under twice this share of its radius (0: never) ..."""
    neck_min_share: Suppress[float] = 0.25
    """... if every part holds at least this share of its pixels ..."""
    part_divergence: Suppress[float] = 1.0
    """... and the parts kept apart if their tracks part by more than this many times their summed sizes"""
    apart_presence: Suppress[float] = 0.2
    """a mover whose zone holds two such parts (outside the other movers) in this share of the latents
    is tracked again as parts from the latent where they are most even (above 1: never)"""
    max_objects: Suppress[int] = 6
    """at most this many moving objects get seeds and a rigid body"""
    max_candidates: Suppress[int] = 10
    """at most this many evidence regions are tracked"""
    refresh_candidates: Suppress[int] = 3
    """at most this many new regions are tracked at the evidence refresh"""
    refresh_margin: Suppress[float] = 0.03
    """at the refresh, evidence within this fraction of the width of a known object's mask is its own"""
    still_shift: float = 0.5
    """a mover strays this many of its radii from its static ray in some latent"""
    still_shift_fraction: Suppress[float] = 0.05
    """... and at least this fraction of the image width"""
    still_shift_cap: float = 0.07
    """... but need not exceed this fraction of the image width"""
    held_presence: Suppress[float] = 0.75
    """a region whose rigid silhouette fits in this share of the latents needs only the floor
    (``still_shift_fraction``; above 1: never)"""
    min_presence: Suppress[float] = 0.4
    """a mover's evidence is found in at least this share of the latents"""
    min_object_iou: Suppress[float] = 0.3
    """a mover's tracked silhouette overlaps its evidence by at least this mean IoU ..."""
    steady_presence: Suppress[float] = 0.75
    """... unless its evidence is found in this share of the latents (e.g. a deforming object)"""
    steady_shift: Suppress[float] = 1.0
    """such a region must stray this many of its radii instead of ``still_shift``"""
    steady_iou: Suppress[float] = 0.15
    """... and its silhouette still overlap its evidence by this mean IoU (below it drifted off)"""
    min_view_support: Suppress[float] = 0.6
    """a mover's evidence lies where at least this share of the clip's typical number of training
    views sees the static surface (under it, the static model is fitted from few views there)"""


def dilate(masks: Bool[Tensor, "... H W"], pixels: int) -> Bool[Tensor, "... H W"]:
    """Masks grown by ``pixels`` in every direction (a square of side 2·pixels + 1)."""
    shape = masks.shape
    flat = masks.reshape(-1, 1, *shape[-2:]).float()
    return (F.max_pool2d(flat, 2 * pixels + 1, stride=1, padding=pixels) > 0.5).reshape(shape)


def box_filter(images: Float[Tensor, "N H W"], size: int) -> Float[Tensor, "N H W"]:
    """Mean over a size x size window (borders average the pixels inside the image)."""
    return F.avg_pool2d(images[:, None], size, stride=1, padding=size // 2, count_include_pad=False)[:, 0]


def filter_size(width: int, fraction: float) -> int:
    """Odd box-filter size of about ``fraction`` of the image width, at least 3 px."""
    size = max(3, int(round(fraction * width)))
    return size if size % 2 == 1 else size + 1


def robust_level(values: Tensor) -> Tuple[float, float]:
    """Median and σ_MAD (1.4826 · median absolute deviation) of all values (a fixed sample of
    2^24 of them on big clips)."""
    flat = values.flatten()
    if flat.numel() > 1 << 24:  # quantile/median on a sample keeps big clips cheap
        flat = flat[torch.randperm(flat.numel(), generator=torch.Generator().manual_seed(0))[: 1 << 24].to(flat.device)]
    median = flat.median()
    return float(median), MAD_TO_SIGMA * float((flat - median).abs().median())


def background_level(values: Tensor, median: float, sigma: float, mads: float, rounds: int) -> Tuple[float, float]:
    """Median and σ_MAD of the background: taken again over the values under median + ``mads`` σ,
    ``rounds`` times, from the level (median, sigma) of all values."""
    flat = values.flatten()
    for _ in range(rounds):
        kept = flat[flat <= median + mads * sigma]
        if kept.numel() == 0:
            break
        median, sigma = robust_level(kept)
    return median, sigma


class Evidence(NamedTuple):
    """Motion evidence per latent: ``mask`` [N, H, W] 0/1 float, the strong ``threshold`` on the
    filtered residual (colour units), and ``background_ratio``: the background's σ over the clip's
    when the grow levels were taken on the background (a large mover), else None."""

    mask: Float[Tensor, "N H W"]
    threshold: float
    background_ratio: Optional[float] = None

    def summary(self) -> str:
        """One line for the training log."""
        line = f"motion evidence on {100.0 * float(self.mask.mean()):.1f}% of pixels (residual > {self.threshold:.3f}"
        if self.background_ratio is not None:
            line += f"; grown on the background's levels, its σ {self.background_ratio:.2f} of the clip's: a large mover"
        return line + ")"


def motion_evidence(residual: Float[Tensor, "N H W"], config: DynamicSeedingConfig) -> Evidence:
    """Binary (0/1 float) motion evidence per latent from the per-pixel mean absolute colour
    residual of the static render, with the threshold used (``Evidence``).

    Pixels whose coarse (``window_fraction``) box-filtered residual is over median +
    ``threshold_mads`` σ are evidence; with hysteresis (``grow_mads`` < ``threshold_mads``) the
    evidence grows into the connected pixels over median + ``grow_mads`` σ, kept where the 3 px
    filtered residual is over its own median + ``trim_mads`` σ (the coarse filter's halo around an
    object is not the object), with gaps of a few pixels closed and holes filled. When a mover is
    big enough to inflate the clip's σ (the background's σ, ``background_level``, under
    ``background_sigma_ratio`` of it), the grow and trim levels are the background's."""
    if residual.dim() != 3:
        raise ValueError(f"motion_evidence: residual must be [N, H, W], got {tuple(residual.shape)}")
    residual = residual.float()
    filtered = box_filter(residual, filter_size(residual.shape[-1], config.window_fraction))
    median, sigma = robust_level(filtered)
    threshold = max(median + config.threshold_mads * sigma, config.min_threshold)
    strong = filtered > threshold
    if config.grow_mads >= config.threshold_mads:
        return Evidence(strong.float(), threshold)
    fine = box_filter(residual, FINE_WINDOW)
    fine_median, fine_sigma = robust_level(fine)
    back_median, back_sigma = background_level(filtered, median, sigma, config.background_mads, config.background_rounds)
    ratio = back_sigma / sigma if sigma > 0 else 1.0
    background = ratio < config.background_sigma_ratio  # a large mover inflates the clip's σ: grow on the background's
    if background:
        median, sigma = back_median, back_sigma
        fine_median, fine_sigma = background_level(fine, fine_median, fine_sigma, config.background_mads, config.background_rounds)
    weak = filtered > min(median + config.grow_mads * sigma, threshold)
    grown = grow_regions(strong, weak, fine > fine_median + config.trim_mads * fine_sigma).float()
    return Evidence(grown, threshold, ratio if background else None)


def grow_regions(strong: Bool[Tensor, "N H W"], weak: Bool[Tensor, "N H W"], keep: Bool[Tensor, "N H W"]) -> Bool[Tensor, "N H W"]:
    """Hysteresis per image: the 8-connected regions of ``weak`` that hold a ``strong`` pixel, kept
    where ``keep`` (plus the strong pixels), closed over ``CLOSING_STEPS`` px gaps, holes filled."""
    grown = torch.zeros_like(strong)
    for i in range(strong.shape[0]):
        hot = strong[i].cpu().numpy()
        if not hot.any():
            continue
        labels, _ = ndimage.label(weak[i].cpu().numpy() | hot, structure=EIGHT_CONNECTED)
        ids = np.unique(labels[hot])
        region = np.isin(labels, ids[ids > 0]) & keep[i].cpu().numpy()
        region = ndimage.binary_closing(region, structure=EIGHT_CONNECTED, iterations=CLOSING_STEPS)
        grown[i] = torch.from_numpy(ndimage.binary_fill_holes(region) | hot).to(strong.device)
    return grown


class Seeds(NamedTuple):
    """Dynamic seeds: points [S, 3] world units, colours [S, 3] in [0, 1], radii [S] world units,
    and the centre [3] of the blob they came from (at the cap's centre depth)."""

    points: Tensor
    colors: Tensor
    radii: Tensor
    centre: Tensor


def seed_gaussians(
    evidence: Float[Tensor, "H W"],
    depth: Float[Tensor, "H W"],
    rgb: Float[Tensor, "H W 3"],
    K: Float[Tensor, "3 3"],
    cam_to_world_cv: Float[Tensor, "4 4"],
    config: DynamicSeedingConfig,
    centre_depth: Optional[float] = None,
) -> Seeds:
    """Back-project evidence pixels of one latent.

    Args:
        evidence: 0/1 motion evidence of the latent.
        depth: static render's expected depth (camera z, world units); pixels without depth are skipped.
        rgb: colours in [0, 1] (the EDI latent).
        K: pinhole intrinsics in pixels.
        cam_to_world_cv: camera-to-world with OpenCV axes (x right, y down, z forward).
        centre_depth: camera depth of the blob's centre (cap shape); default: the blob's median
            static depth times ``depth_scale``.
    """
    stride = max(1, config.pixel_stride)
    inside = (evidence > 0.5) & (depth > 0) & torch.isfinite(depth)
    keep = torch.zeros_like(evidence, dtype=torch.bool)
    keep[::stride, ::stride] = True
    keep &= inside
    v, u = torch.nonzero(keep, as_tuple=True)
    if len(v) > config.max_seeds:
        pick = torch.linspace(0, len(v) - 1, config.max_seeds, device=v.device).round().long()
        v, u = v[pick], u[pick]
    blob_v, blob_u = torch.nonzero(inside, as_tuple=True)
    if len(blob_v) == 0:
        empty = depth.new_zeros(0, 3)
        return Seeds(empty, empty.clone(), depth.new_zeros(0), depth.new_zeros(3))
    centre_u, centre_v = blob_u.to(depth.dtype).mean(), blob_v.to(depth.dtype).mean()
    z_centre = depth[blob_v, blob_u].median() * config.depth_scale if centre_depth is None else depth.new_tensor(centre_depth)
    if config.seed_shape == "cap":
        radius_px = (len(blob_v) / torch.pi) ** 0.5
        radius = radius_px * z_centre / K[0, 0]
        rho = torch.hypot(u.to(depth.dtype) - centre_u, v.to(depth.dtype) - centre_v) / radius_px
        z = z_centre - radius * (1.0 - rho.square()).clamp_min(0.0).sqrt()
    else:
        z = depth[v, u] * config.depth_scale
    points = backproject(u, v, z, K, cam_to_world_cv)
    radii = config.scale_pixels * stride * z / K[0, 0]
    centre = backproject(centre_u[None], centre_v[None], z_centre[None], K, cam_to_world_cv)[0]
    return Seeds(points, rgb[v, u].clamp(0.0, 1.0), radii, centre)


def backproject(u: Tensor, v: Tensor, z: Tensor, K: Tensor, cam_to_world_cv: Tensor) -> Tensor:
    """World points [S, 3] of pixel coordinates u, v (pixel indices; centres at +0.5) at camera depth z."""
    x = (u.to(z.dtype) + PIXEL_CENTRE - K[0, 2]) / K[0, 0] * z
    y = (v.to(z.dtype) + PIXEL_CENTRE - K[1, 2]) / K[1, 1] * z
    return torch.stack([x, y, z], dim=-1) @ cam_to_world_cv[:3, :3].T + cam_to_world_cv[:3, 3]


def evidence_track(
    evidence: Float[Tensor, "N H W"],
    depths: Float[Tensor, "N H W"],
    Ks: Float[Tensor, "N 3 3"],
    cams_to_world_cv: Float[Tensor, "N 4 4"],
    config: DynamicSeedingConfig,
) -> Tuple[Tensor, Tensor]:
    """3D track of the evidence blob: for each latent with at least ``min_object_fraction`` of its
    pixels as evidence, its centroid back-projected at the blob's median static depth times ``depth_scale``.

    Returns:
        indices [T] of the latents with a track point, points [T, 3] world units.
    """
    indices, points = [], []
    for i in range(evidence.shape[0]):
        v, u = torch.nonzero(evidence[i] > 0.5, as_tuple=True)
        if len(v) < max(1, round(config.min_object_fraction * evidence[i].numel())):
            continue
        z = depths[i, v, u]
        z = z[torch.isfinite(z) & (z > 0)]
        if len(z) == 0:
            continue
        centre_u, centre_v = u.float().mean(), v.float().mean()
        depth = z.median() * config.depth_scale
        points.append(backproject(centre_u[None], centre_v[None], depth[None], Ks[i], cams_to_world_cv[i])[0])
        indices.append(i)
    if not points:
        return torch.zeros(0, dtype=torch.long), torch.zeros(0, 3)
    return torch.tensor(indices, dtype=torch.long), torch.stack(points)


def fit_motion(
    deformation: torch.nn.Module,
    seeds: Float[Tensor, "S 3"],
    times: Float[Tensor, "T"],
    offsets: Tensor,
    config: DynamicSeedingConfig,
    generator: Optional[torch.Generator] = None,
) -> List[float]:
    """Regress ``deformation(seeds, t)`` onto the offsets (Δμ = offsets, Δq = Δs = 0) with a private
    Adam (the training optimizer's moments are left alone); returns the loss per step.

    Args:
        offsets: [T, 3] one offset per time for every seed (a translation track) or [T, S, 3] one
            per time and seed (a rigid track with rotation).
    """
    if len(seeds) == 0 or len(times) == 0 or config.init_motion_steps <= 0:
        return []
    params = [p for p in deformation.parameters()]
    optimizer = torch.optim.Adam(params, lr=config.init_motion_lr)
    generator = generator or torch.Generator().manual_seed(0)
    per_time = max(1, config.init_motion_batch // max(1, min(len(times), 8)))
    history = []
    with torch.enable_grad():
        for _ in range(config.init_motion_steps):
            pick_t = torch.randint(len(times), (min(len(times), 8),), generator=generator)
            loss = seeds.new_zeros(())
            for j in pick_t.tolist():
                rows = torch.randint(len(seeds), (min(per_time, len(seeds)),), generator=generator).to(seeds.device)
                d_xyz, d_rot, d_scale = deformation(seeds[rows], float(times[j]))
                target = offsets[j] if offsets.dim() == 2 else offsets[j, rows]
                loss = loss + (d_xyz - target).square().sum(-1).mean() + d_rot.square().sum(-1).mean() + d_scale.square().sum(-1).mean()
            loss = loss / len(pick_t)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            history.append(float(loss))
    for p in params:
        p.grad = None
    return history

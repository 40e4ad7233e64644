"""Evaluate a trained EDyGS run: input-view deblurring, novel views, motion masks and poses.

`evaluate_run(config_path, output_dir)` loads a run with nerfstudio's `eval_setup`, then

* **input views** (deblurring): every training latent is rendered at its *refined* pose and its
  time and compared with the ground-truth sharp image of that instant. For a model trained on
  the blurry frames (`edygs-blurry`) the latent instants come from the same scene read with
  `image_source="latent"`, rendered at their dataparser poses. The EDI latents and the blurry
  inputs are scored against the same ground truth as references (rows "EDI latent", "blurry
  input").
* **novel views**: the evaluation cameras (the ground-truth novel views) at their times. Their
  ground-truth poses are first moved into the model's frame by the Sim(3) that maps the
  ground-truth training poses onto the refined ones (edygs_ns.eval.pose_alignment explains why),
  then each pose is fitted to its image with the model frozen (edygs_ns.eval.novel_pose_fit;
  ``novel_pose_fit.steps = 0`` turns that off). The report gives the mean correction. When the
  poses were fitted, the same cameras are also scored as mapped, without fitting (row
  "novel views (no pose fit)": what ``ns-render camera-path`` renders from true novel cameras).
* **poses**: ATE / RPE of the initial (dataparser) and the refined training poses against the
  ground truth after Sim(3) Umeyama alignment, in the ground truth's own units (the dataparser's
  scale and the scale that moved the ground truth into COLMAP's frame are undone), and ATE as a
  fraction of the trajectory extent.

Metrics: PSNR, SSIM (edygs_ns.eval.metrics), LPIPS with AlexNet and VGG (reported unavailable,
never zero, when the backbone weights are missing), motion-mask IoU against the ground-truth
dynamic masks, and the mean rendered motion mask ("mask_mean", JSON only: near 0 where nothing
moves). Written files, under `output_dir`:

    metrics.json, metrics.md         the table (edygs_ns.eval.report), per-view values in the JSON
    grids/{input,novel}_NNNN.png     blurry input | EDI latent | ours | ground truth | motion mask |
                                     GT motion mask, one file per selected view
    grids/{input,novel}_overview.png the selected views of a split stacked in one grid
    trajectory.png                   GT, initial and refined camera centres (aligned to GT)
    psnr_over_time_{input,novel}.png per-view PSNR against time
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Dict, List, Literal, Mapping, Optional, Sequence, Tuple

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.utils.rich_utils import CONSOLE, get_progress
from PIL import Image
from torch import Tensor

from edygs_ns.io.images import UINT8_MAX, read_rgb_uint8
from edygs_ns.eval.figures import plot_psnr_over_time, plot_trajectories, save_grid
from edygs_ns.eval.lpips_loader import LpipsMetric, lpips_or_none
from edygs_ns.eval.metrics import MetricSet
from edygs_ns.eval.novel_pose_fit import NovelPoseFitConfig, fit_camera_pose
from edygs_ns.eval.pose_alignment import (
    INITIAL_POSES_SPLIT,
    POSE_METRIC_KEYS,
    REFINED_POSES_SPLIT,
    Sim3,
    TrainPoses,
    align_cameras,
    anchor_to_training,
    camera_path_json,
    novel_alignment,
    pose_rows,
    refined_train_poses,
    scale_translations,
    with_poses,
)
from edygs_ns.eval.report import DEFAULT_NOTES, markdown_table, write_metrics
from edygs_ns.geometry import align_poses, apply_sim3, rotation_angle, to_homogeneous
from edygs_ns.losses.metrics import mask_iou, psnr, ssim

EvalSplit = Literal["input", "novel", "both"]

#: Row (split) names of the metrics table.
INPUT_SPLIT = "input views"
NOVEL_SPLIT = "novel views"
#: The novel cameras as mapped by the training-camera Sim(3), without per-view pose fitting
#: (written only when NOVEL_SPLIT's poses were fitted; otherwise NOVEL_SPLIT is this protocol).
NOVEL_UNFITTED_SPLIT = "novel views (no pose fit)"
#: The same cameras, each placed relative to its nearest training latent (``anchor_to_training``).
NOVEL_ANCHORED_SPLIT = "novel views (anchored)"
#: Method rows of the reference images scored against the same ground truth as the input views.
EDI_REFERENCE = "EDI latent"
BLURRY_REFERENCE = "blurry input"
#: Metric keys every image split carries (a number summary, or a reason string when unavailable).
IMAGE_METRIC_KEYS: Tuple[str, ...] = ("psnr", "ssim", "lpips_alex", "lpips_vgg", "mask_iou")
#: PSNR over the true moving object and over the rest, where the scene has ground-truth masks.
REGION_PSNR_KEYS: Tuple[str, ...] = ("psnr_dynamic", "psnr_static")
#: Novel views: PSNR over the pixels some training latent saw (simulator scenes; sim/covisibility.py).
COVISIBLE_PSNR_KEY = "psnr_covisible"
#: Novel views: PSNR over the pixels no training latent saw, and their share of the view's squared error.
UNSEEN_PSNR_KEY = "psnr_unseen"
UNSEEN_ERROR_SHARE_KEY = "unseen_error_share"
COVISIBILITY_KEYS: Tuple[str, ...] = (COVISIBLE_PSNR_KEY, UNSEEN_PSNR_KEY, UNSEEN_ERROR_SHARE_KEY)
#: LPIPS backbones reported (metric key "lpips_<net>").
LPIPS_NETS: Tuple[str, ...] = ("alex", "vgg")
#: Columns of the per-view grids.
GRID_COLUMNS: Tuple[str, ...] = ("blurry input", "EDI latent", "ours", "ground truth", "motion mask", "GT motion mask")
#: Output names inside the output folder.
GRID_DIR = "grids"
TRAJECTORY_PNG = "trajectory.png"
#: ns-render camera-path file of the mapped novel cameras (what "novel views (no pose fit)" scores).
NOVEL_CAMERA_PATH = "novel_camera_path.json"
PSNR_PNG_PATTERN = "psnr_over_time_{slug}.png"
OVERVIEW_SUFFIX = "overview"
#: Default number of views per split drawn as grids (evenly spaced); negative draws all.
DEFAULT_MAX_GRIDS = 8
#: Level at which the rendered motion mask counts as dynamic for the IoU, and GT masks are binarised.
MASK_THRESHOLD = 0.5
#: Per-view values stored in metrics.json under this key of each image split.
PER_VIEW_KEY = "per_view"


@dataclass
class ViewGroup:
    """The views of one split: cameras at the poses to render and the files to compare with.

    Attributes:
        name: split name in the table (INPUT_SPLIT or NOVEL_SPLIT).
        slug: short name used in file names ("input", "novel").
        cameras: [V] cameras in the model's frame, with `times`.
        gt_images: V ground-truth sharp images, or None (nothing to compare with).
        gt_masks: V ground-truth motion masks (white = dynamic), or None.
        gt_covisible: V maps of how many training latents saw each pixel (novel views), or None.
        edi_images: V EDI latent images (input views), or None.
        blurry_images: V blurry input frames the views belong to (input views), or None.
        note: how the poses were chosen, for the report.
    """

    name: str
    slug: str
    cameras: Cameras
    gt_images: Optional[List[Path]]
    gt_masks: Optional[List[Path]] = None
    gt_covisible: Optional[List[Path]] = None
    edi_images: Optional[List[Path]] = None
    blurry_images: Optional[List[Path]] = None
    note: str = ""

    @property
    def times(self) -> np.ndarray:
        """[V] normalised times of the views (0 when the cameras carry none)."""
        if self.cameras.times is None:
            return np.zeros(self.cameras.shape[0])
        return self.cameras.times.reshape(-1).detach().cpu().double().numpy()


# ----------------------------------------------------------------------------- loading


def _read_rgb(path: Path) -> Tensor:
    """Image file -> float [H, W, 3] in [0, 1] (alpha dropped; layouts store composited RGB)."""
    return torch.from_numpy(read_rgb_uint8(Path(path)).astype(np.float32) / UINT8_MAX)


def _read_mask(path: Path) -> Tensor:
    """Mask file (white = dynamic) -> bool [H, W]."""
    with Image.open(path) as img:
        return torch.from_numpy(np.asarray(img.convert("L"), dtype=np.float32) / UINT8_MAX >= MASK_THRESHOLD)


def _read_covisible(path: Path) -> Tensor:
    """Co-visibility map (training latents that saw each pixel) -> bool [H, W], seen by at least one."""
    with Image.open(path) as img:
        return torch.from_numpy(np.asarray(img.convert("L")) > 0)


def _file_list(meta: Mapping[str, Any], key: str, count: int) -> Optional[List[Path]]:
    files = meta.get(key)
    if not files:
        return None
    if len(files) != count:
        raise ValueError(f"dataparser metadata {key!r} lists {len(files)} files for {count} cameras")
    return [Path(f) for f in files]


def _is_latent_split(meta: Mapping[str, Any], count: int) -> bool:
    latent = meta.get("latent_index")
    return latent is not None and len(latent) == count and bool((torch.as_tensor(latent) >= 0).all())


def _blurry_per_view(meta: Mapping[str, Any], count: int) -> Optional[List[Path]]:
    blurry = meta.get("blurry_filenames")
    index = meta.get("blurry_index")
    if not blurry or index is None or len(index) != count:
        return None
    return [Path(blurry[int(b)]) for b in torch.as_tensor(index).tolist()]


def input_views(pipeline: Any) -> Tuple[ViewGroup, TrainPoses]:
    """Input-view group (training latents at refined poses) and the training poses.

    Args:
        pipeline: a loaded nerfstudio pipeline with the edygs-data dataparser.

    Returns:
        (ViewGroup of INPUT_SPLIT, TrainPoses).
    """
    dm = pipeline.datamanager
    outputs = dm.train_dataparser_outputs
    meta = outputs.metadata
    cameras = dm.train_dataset.cameras
    count = cameras.shape[0]
    if _is_latent_split(meta, count):
        refined = refined_train_poses(pipeline.model, cameras)
        edi = [Path(f) for f in outputs.image_filenames]
        note = "training latents at their refined poses"
        refined_note = ""
    else:
        # The model was trained on other cameras (the blurry-frame baseline): score it at the latent
        # instants of the same scene, at their dataparser poses (same transform, same frame).
        latent_config = replace(dm.dataparser.config, image_source="latent")
        outputs = latent_config.setup().get_dataparser_outputs(split="train")
        meta = outputs.metadata
        cameras = outputs.cameras
        count = cameras.shape[0]
        refined = cameras.camera_to_worlds.clone()
        edi = [Path(f) for f in outputs.image_filenames]
        note = "latent instants at their dataparser poses (the model was not trained on latent cameras)"
        refined_note = "the model has no per-latent poses (trained on other cameras)"
    gt_c2w = meta.get("gt_camera_to_worlds")
    # one ground-truth unit in the model frame (older dataparser outputs: the dataparser scale)
    scale = float(meta.get("gt_units_scale", outputs.dataparser_scale))
    poses = TrainPoses(
        initial=to_homogeneous(cameras.camera_to_worlds),
        refined=to_homogeneous(refined),
        gt=None if gt_c2w is None else to_homogeneous(gt_c2w),
        scale=scale,
        refined_note=refined_note,
    )
    group = ViewGroup(
        name=INPUT_SPLIT,
        slug="input",
        cameras=with_poses(cameras, refined),
        gt_images=_file_list(meta, "gt_image_filenames", count),
        gt_masks=_file_list(meta, "gt_mask_filenames", count),
        edi_images=edi,
        blurry_images=_blurry_per_view(meta, count),
        note=note,
    )
    return group, poses


def novel_views(pipeline: Any, sim3: Optional[Sim3], sim3_note: str) -> ViewGroup:
    """Novel-view group: the evaluation cameras, their ground-truth poses moved by `sim3`.

    Args:
        pipeline: a pipeline loaded with test_mode "test" (its eval dataset holds the novel views).
        sim3: ground-truth -> model frame similarity, or None to render the poses as given.
        sim3_note: how `sim3` was obtained (or why there is none), for the report.
    """
    dataset = pipeline.datamanager.eval_dataset
    meta = dataset.metadata
    cameras = dataset.cameras
    count = cameras.shape[0]
    gt_c2w = meta.get("gt_camera_to_worlds")
    if gt_c2w is not None and sim3 is not None:
        cameras = align_cameras(with_poses(cameras, gt_c2w), sim3)
        note = f"ground-truth novel poses mapped into the model frame ({sim3_note})"
    else:
        cameras = with_poses(cameras, cameras.camera_to_worlds)
        note = f"evaluation cameras as given by the dataparser ({sim3_note or 'no ground-truth poses'})"
    gt = _file_list(meta, "gt_image_filenames", count) or [Path(f) for f in dataset.image_filenames]
    return ViewGroup(name=NOVEL_SPLIT, slug="novel", cameras=cameras, gt_images=gt,
                     gt_masks=_file_list(meta, "gt_mask_filenames", count),
                     gt_covisible=_file_list(meta, "gt_covisible_filenames", count), note=note)  # fmt: skip


def anchored_views(aligned: ViewGroup, inputs: ViewGroup, poses: TrainPoses, sim3: Optional[Sim3]) -> Optional[ViewGroup]:
    """The novel views mapped by ``sim3``, each then placed relative to the training latent nearest
    in time (``anchor_to_training``); None without ground-truth training poses or a Sim(3)."""
    if sim3 is None or poses.gt is None or len(inputs.times) != len(poses.gt):
        return None
    c2w = anchor_to_training(to_homogeneous(aligned.cameras.camera_to_worlds), aligned.times, apply_sim3(poses.gt, sim3),
                             poses.refined, inputs.times)
    return replace(aligned, name=NOVEL_ANCHORED_SPLIT, slug="novel_anchored", cameras=with_poses(aligned.cameras, c2w),
                   note="novel cameras as mapped, each moved by the residual of the training latent nearest in time "
                        "(its refined pose against its mapped ground truth); no per-view pose fitting")


def fit_group_poses(model: Any, group: ViewGroup, config: NovelPoseFitConfig) -> ViewGroup:
    """The group with every camera's pose fitted to its ground-truth image (model frozen).

    Returns the group unchanged when ``config.steps`` is 0 or it has no ground-truth images; the
    returned group's note gives the mean rotation / translation correction and L1 before / after.
    """
    if config.steps <= 0 or group.gt_images is None:
        return group
    cameras = group.cameras.to(model.device)
    fitted, angles, shifts, before, after = [], [], [], [], []
    with get_progress(f"Fitting {group.name} poses ({config.steps} steps each)") as progress:
        for i in progress.track(range(cameras.shape[0]), total=cameras.shape[0]):
            target = _read_rgb(group.gt_images[i]).to(model.device)
            camera, l1_before, l1_after = fit_camera_pose(model, cameras[i : i + 1], target, config)
            change = to_homogeneous(camera.camera_to_worlds) @ np.linalg.inv(to_homogeneous(cameras[i : i + 1].camera_to_worlds))
            angles.append(math.degrees(float(rotation_angle(change[0, :3, :3]))))
            shifts.append(float(np.linalg.norm(camera.camera_to_worlds[0, :3, 3].cpu() - cameras.camera_to_worlds[i, :3, 3].cpu())))
            before.append(l1_before)
            after.append(l1_after)
            fitted.append(camera.camera_to_worlds.detach())
    note = (f"{group.note}; then each pose fitted to its image with the model frozen ({config.steps} Adam steps): "
            f"mean correction {np.mean(angles):.3f} deg, {np.mean(shifts):.4g} model units; "
            f"L1 {np.mean(before):.4f} -> {np.mean(after):.4f}")  # fmt: skip
    return replace(group, cameras=with_poses(group.cameras, torch.cat(fitted).cpu()), note=note)


# ----------------------------------------------------------------------------- poses


def plot_pose_trajectories(path: Path, poses: TrainPoses) -> Optional[Path]:
    """Trajectory figure: GT, initial and refined centres, each Sim(3)-aligned onto GT (ground-truth units)."""
    if poses.gt is None or poses.gt.shape[0] < 3:
        return None
    unscale = 1.0 / poses.scale
    gt = scale_translations(poses.gt, unscale)
    curves: Dict[str, np.ndarray] = {"GT": gt}
    for label, est in (("initial", poses.initial), ("refined", poses.refined)):
        try:
            curves[label], _ = align_poses(scale_translations(est, unscale), gt)
        except ValueError as exc:
            CONSOLE.log(f"[yellow]trajectory plot: {label} poses not drawn: {exc}")
    return plot_trajectories(path, curves, title="camera centres (aligned to GT, ground-truth units)")


# ----------------------------------------------------------------------------- images


def _grid_indices(count: int, max_grids: int) -> List[int]:
    if max_grids < 0 or count <= max_grids:
        return list(range(count))
    if max_grids == 0:
        return []
    return sorted(set(np.linspace(0, count - 1, max_grids).round().astype(int).tolist()))


class _Lpips:
    """LPIPS functions per backbone, or the reason each is unavailable."""

    def __init__(self, weights: Optional[Path], device: torch.device) -> None:
        self.fns: Dict[str, Optional[LpipsMetric]] = {}
        self.reasons: Dict[str, str] = {}
        for net in LPIPS_NETS:
            fn, reason = lpips_or_none(net, weights, device)  # type: ignore[arg-type]
            self.fns[net], self.reasons[net] = fn, reason

    def score(self, pred: Tensor, gt: Tensor, into: Dict[str, float]) -> None:
        """Add lpips_<net> of one view [H, W, 3] to `into` for every usable backbone."""
        for net, fn in self.fns.items():
            if fn is None:
                continue
            try:
                into[f"lpips_{net}"] = float(fn(pred[None], gt[None])[0])
            except ValueError as exc:  # image smaller than the backbone accepts
                self.fns[net], self.reasons[net] = None, str(exc)

    def fill(self, summary: Dict[str, Any]) -> None:
        """Put the reason string under lpips_<net> for every backbone without values."""
        for net in LPIPS_NETS:
            if f"lpips_{net}" not in summary:
                summary[f"lpips_{net}"] = self.reasons.get(net) or "LPIPS not computed"


def _to_numpy(image: Tensor) -> np.ndarray:
    return image.detach().float().cpu().clamp(0.0, 1.0).numpy()


def region_psnr(pred: Tensor, gt: Tensor, dynamic: Optional[Tensor]) -> Dict[str, float]:
    """PSNR over the true dynamic region and over the rest ("psnr_dynamic", "psnr_static").

    Args:
        pred, gt: [H, W, 3] images in [0, 1].
        dynamic: [H, W] bool ground-truth motion mask, or None.

    Returns:
        The two values, or fewer: a region with no pixel (or no mask) is left out.
    """
    if dynamic is None:
        return {}
    dynamic = dynamic.to(pred.device)
    out: Dict[str, float] = {}
    for key, region in (("psnr_dynamic", dynamic), ("psnr_static", ~dynamic)):
        if bool(region.any()):
            out[key] = psnr(pred, gt, mask=region)
    return out


def covisibility_scores(pred: Tensor, gt: Tensor, seen: Tensor) -> Dict[str, float]:
    """Scores split by co-visibility: PSNR over the seen and the unseen pixels, and the unseen
    pixels' share of the view's summed squared error (0-1; what no training view could teach).

    Args:
        pred, gt: [H, W, 3] images in [0, 1].
        seen: [H, W] bool, true where some training latent saw the surface.

    Returns:
        The COVISIBILITY_KEYS values; a region without pixels is left out.
    """
    seen = seen.to(pred.device).bool()
    out: Dict[str, float] = {}
    if bool(seen.any()):
        out[COVISIBLE_PSNR_KEY] = psnr(pred, gt, mask=seen)
    if bool((~seen).any()):
        out[UNSEEN_PSNR_KEY] = psnr(pred, gt, mask=~seen)
        error = ((pred.float() - gt.float()) ** 2).sum(dim=-1)
        total = float(error.sum())
        out[UNSEEN_ERROR_SHARE_KEY] = float(error[~seen].sum()) / total if total > 0 else 0.0
    return out


def _score_reference(
    files: Optional[List[Path]], index: int, gt: Tensor, into: MetricSet, dynamic: Optional[Tensor] = None
) -> Optional[Tensor]:
    """PSNR/SSIM (and region PSNRs) of a reference image (EDI latent, blurry input) against the ground truth."""
    if files is None:
        return None
    image = _read_rgb(files[index])
    if image.shape == gt.shape:
        into.update({"psnr": psnr(image, gt), "ssim": ssim(image, gt), **region_psnr(image, gt, dynamic)})
    return image


def evaluate_group(
    model: Any, group: ViewGroup, lpips: _Lpips, grid_dir: Optional[Path], max_grids: int
) -> Tuple[Dict[str, Any], Dict[str, Dict[str, Any]]]:
    """Render every view of `group`, score it, draw grids for the selected views.

    Returns:
        (values of the split: IMAGE_METRIC_KEYS summaries or reason strings, "n", "note" and
        per-view lists under PER_VIEW_KEY; reference rows {method: values} for the EDI latents
        and blurry inputs, empty for novel views).
    """
    count = group.cameras.shape[0]
    times = group.times
    ours, edi_set, blurry_set = MetricSet(), MetricSet(), MetricSet()
    per_view: Dict[str, List[Any]] = {"time": times.tolist()}
    wanted = set(_grid_indices(count, max_grids))
    grid_rows: List[Dict[str, np.ndarray]] = []
    grid_views: List[int] = []
    labels: List[str] = []
    cameras = group.cameras.to(model.device)
    # ablations without the motion-mask field render an all-zero mask: nothing to score
    renders_mask = bool(getattr(getattr(model, "config", None), "use_motion_mask", True))
    with get_progress(f"Rendering {group.name}") as progress:
        for i in progress.track(range(count), total=count):
            outputs = model.get_outputs_for_camera(cameras[i : i + 1])
            pred = outputs["rgb"].detach()
            mask = outputs.get("mask") if renders_mask else None
            row: Dict[str, np.ndarray] = {"ours": _to_numpy(pred)}
            if mask is not None:
                row["motion mask"] = _to_numpy(mask[..., 0])
            if group.gt_images is not None:
                gt = _read_rgb(group.gt_images[i]).to(pred.device)
                if gt.shape != pred.shape:
                    raise ValueError(f"{group.gt_images[i]}: ground truth is {tuple(gt.shape)}, the render is {tuple(pred.shape)}")
                values = {"psnr": psnr(pred, gt), "ssim": ssim(pred, gt)}
                lpips.score(pred, gt, values)
                row["ground truth"] = _to_numpy(gt)
                gt_mask = None
                if group.gt_masks is not None:
                    gt_mask = _read_mask(group.gt_masks[i])
                    row["GT motion mask"] = gt_mask.float().numpy()
                    values.update(region_psnr(pred, gt, gt_mask))
                    if mask is not None:
                        values["mask_iou"] = mask_iou(mask[..., 0].detach().cpu(), gt_mask, MASK_THRESHOLD)
                if group.gt_covisible is not None:
                    values.update(covisibility_scores(pred, gt, _read_covisible(group.gt_covisible[i])))
                if mask is not None:
                    values["mask_mean"] = float(mask.detach().float().mean())
                ours.update(values)
                edi = _score_reference(group.edi_images, i, gt.cpu(), edi_set, gt_mask)
                blurry = _score_reference(group.blurry_images, i, gt.cpu(), blurry_set, gt_mask)
            else:
                edi = _read_rgb(group.edi_images[i]) if group.edi_images is not None else None
                blurry = _read_rgb(group.blurry_images[i]) if group.blurry_images is not None else None
                if mask is not None:
                    ours.add("mask_mean", float(mask.detach().float().mean()))
            if i in wanted:
                if edi is not None:
                    row["EDI latent"] = edi.numpy()
                if blurry is not None:
                    row["blurry input"] = blurry.numpy()
                grid_rows.append(row)
                grid_views.append(i)
                labels.append(f"#{i} t={times[i]:.3f}")
    for name, values in ours.values.items():
        per_view[name] = values
    summary = _summarise(ours, group, lpips)
    summary.update({"n": count, "note": group.note, PER_VIEW_KEY: per_view})
    if grid_dir is not None:
        _save_grids(grid_dir, group.slug, grid_rows, labels, grid_views)
    references: Dict[str, Dict[str, Any]] = {}
    for label, reference in ((EDI_REFERENCE, edi_set), (BLURRY_REFERENCE, blurry_set)):
        if reference.values:
            references[label] = dict(reference.summary(), **{PER_VIEW_KEY: {"time": times.tolist(), **reference.values}})
    return summary, references


def _summarise(ours: MetricSet, group: ViewGroup, lpips: _Lpips) -> Dict[str, Any]:
    """Mean/std/n of every metric of a split; a reason string for each metric without values."""
    summary: Dict[str, Any] = dict(ours.summary())
    missing = "no ground-truth images" if group.gt_images is None else None
    for key in ("psnr", "ssim"):
        summary.setdefault(key, missing)
    if missing:
        summary.update({f"lpips_{net}": missing for net in LPIPS_NETS})
    lpips.fill(summary)
    if "mask_iou" not in summary:
        summary["mask_iou"] = missing or ("no ground-truth motion masks" if group.gt_masks is None else "the model renders no motion mask")
    return summary


def _save_grids(grid_dir: Path, slug: str, rows: List[Dict[str, np.ndarray]], labels: List[str], views: List[int]) -> None:
    """One grid per selected view ({slug}_NNNN.png) and all of them stacked ({slug}_overview.png)."""
    if not rows:
        return
    columns = [c for c in GRID_COLUMNS if any(c in r for r in rows)]
    for row, label, index in zip(rows, labels, views):
        save_grid(grid_dir / f"{slug}_{index:04d}.png", [row], columns, row_labels=[label])
    save_grid(grid_dir / f"{slug}_{OVERVIEW_SUFFIX}.png", rows, columns, row_labels=labels)


# ----------------------------------------------------------------------------- entry point


def _load(config_path: Path) -> Tuple[Any, Any, Path, int]:
    from nerfstudio.utils.eval_utils import eval_setup

    from edygs_ns.compat import allow_nerfstudio_checkpoints

    allow_nerfstudio_checkpoints()
    config_path = Path(config_path)
    if not config_path.is_file():
        raise FileNotFoundError(f"edygs-eval: run config {config_path} does not exist (pass RUN/config.yml)")
    return eval_setup(config_path, test_mode="test")


def evaluate_pipeline(
    pipeline: Any,
    output_dir: Path,
    method: str,
    split: EvalSplit = "both",
    lpips_weights: Optional[Path] = None,
    max_grids: int = DEFAULT_MAX_GRIDS,
    align_novel: bool = True,
    extra_notes: Sequence[str] = (),
    novel_pose_fit: Optional[NovelPoseFitConfig] = None,
) -> Dict[str, Dict[str, Dict[str, Any]]]:
    """Evaluate an already loaded pipeline (see `evaluate_run`)."""
    if split not in ("input", "novel", "both"):
        raise ValueError(f"split must be 'input', 'novel' or 'both', got {split!r}")
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    model = pipeline.model
    model.eval()
    lpips = _Lpips(lpips_weights, model.device)
    group, poses = input_views(pipeline)
    rows: Dict[str, Dict[str, Any]] = {}
    references: Dict[str, Dict[str, Any]] = {}
    notes: List[str] = list(extra_notes)
    grid_dir = output_dir / GRID_DIR
    psnr_plots: List[Tuple[ViewGroup, Dict[str, Any], Dict[str, Dict[str, Any]]]] = []
    if split in ("input", "both"):
        rows[INPUT_SPLIT], references = evaluate_group(model, group, lpips, grid_dir, max_grids)
        psnr_plots.append((group, rows[INPUT_SPLIT], references))
        notes.append(f"{INPUT_SPLIT}: {group.note}; {EDI_REFERENCE} / {BLURRY_REFERENCE} rows score those images against the same ground truth.")
    if split in ("novel", "both"):
        sim3, sim3_note = novel_alignment(poses, align_novel)
        aligned = novel_views(pipeline, sim3, sim3_note)
        (output_dir / NOVEL_CAMERA_PATH).write_text(json.dumps(camera_path_json(aligned.cameras), indent=1))
        notes.append(f"{NOVEL_CAMERA_PATH}: the novel cameras as mapped, for ns-render camera-path (no pose fitting).")
        novel = fit_group_poses(model, aligned, novel_pose_fit or NovelPoseFitConfig())
        rows[NOVEL_SPLIT], _ = evaluate_group(model, novel, lpips, grid_dir, max_grids)
        psnr_plots.append((novel, rows[NOVEL_SPLIT], {}))
        notes.append(f"{NOVEL_SPLIT}: {novel.note}.")
        if novel is not aligned:  # poses were fitted: also score the cameras as mapped (no grids)
            unfitted = replace(aligned, name=NOVEL_UNFITTED_SPLIT, slug="novel_nofit")
            rows[NOVEL_UNFITTED_SPLIT], _ = evaluate_group(model, unfitted, lpips, None, max_grids)
            notes.append(f"{NOVEL_UNFITTED_SPLIT}: {aligned.note}; no per-view pose fitting.")
        anchored = anchored_views(aligned, group, poses, sim3)
        if anchored is not None:
            rows[NOVEL_ANCHORED_SPLIT], _ = evaluate_group(model, anchored, lpips, None, max_grids)
            notes.append(f"{NOVEL_ANCHORED_SPLIT}: {anchored.note}.")
    rows.update(pose_rows(poses))
    notes.append("Poses: ATE / RPE in the ground truth's units; ate_frac = ATE / largest "
                 "distance between two ground-truth camera centres (in metrics.json).")  # fmt: skip
    for net in LPIPS_NETS:
        fn = lpips.fns.get(net)
        notes.append(f"LPIPS({net}): " + (f"weights {fn.weights_file}" if fn is not None else f"unavailable: {lpips.reasons.get(net)}"))
    metrics: Dict[str, Dict[str, Dict[str, Any]]] = {method: rows}
    for label, values in references.items():
        metrics[label] = {INPUT_SPLIT: values}
    json_path, md_path = write_metrics(output_dir, metrics, notes=list(notes) + list(DEFAULT_NOTES), title=f"Evaluation of {method}")
    plot_pose_trajectories(output_dir / TRAJECTORY_PNG, poses)
    for view_group, values, refs in psnr_plots:
        per_view = values[PER_VIEW_KEY]
        if "psnr" not in per_view:
            continue
        lines = {method: per_view["psnr"]}
        lines.update({label: ref[PER_VIEW_KEY]["psnr"] for label, ref in refs.items() if "psnr" in ref[PER_VIEW_KEY]})
        plot_psnr_over_time(output_dir / PSNR_PNG_PATTERN.format(slug=view_group.slug), per_view["time"], lines,
                            title=f"{view_group.name}: PSNR over time")  # fmt: skip
    for line in markdown_table(metrics):
        CONSOLE.print(line, markup=False, highlight=False, soft_wrap=True)
    CONSOLE.log(f"edygs-eval: wrote {json_path}, {md_path} and figures under {output_dir}")
    return metrics


def evaluate_run(
    config_path: Path,
    output_dir: Path,
    lpips_weights: Optional[Path] = None,
    split: EvalSplit = "both",
    max_grids: int = DEFAULT_MAX_GRIDS,
    align_novel: bool = True,
    method: Optional[str] = None,
    novel_pose_fit: Optional[NovelPoseFitConfig] = None,
) -> Dict[str, Dict[str, Dict[str, Any]]]:
    """Load a trained run and evaluate it; writes metrics.json, metrics.md and figures.

    Args:
        config_path: RUN/config.yml written by ns-train.
        output_dir: folder for the outputs (created).
        lpips_weights: torchvision backbone weights (.pth file or a folder holding them) for
            LPIPS; see edygs_ns.eval.lpips_loader for where else they are looked for.
        split: "input" (deblurring of the training latents), "novel" or "both".
        max_grids: views per split drawn as grids, evenly spaced (negative: all, 0: none).
        align_novel: move the ground-truth novel cameras into the model's frame by the Sim(3)
            fitted between ground-truth and refined training poses.
        method: row label of the run; default the run's method name (e.g. "edygs").
        novel_pose_fit: test-time fitting of the novel cameras' poses (default
            NovelPoseFitConfig(); steps 0 renders the aligned poses as they are).

    Returns:
        The metrics as written to metrics.json: {method: {split: {metric: value}}}. The run's
        rows are INPUT_SPLIT / NOVEL_SPLIT (IMAGE_METRIC_KEYS; each value {"mean", "std", "n"}
        or a reason string when unavailable; per-view values under PER_VIEW_KEY), with
        NOVEL_UNFITTED_SPLIT when the novel poses were fitted, and
        INITIAL_POSES_SPLIT / REFINED_POSES_SPLIT (POSE_METRIC_KEYS, floats or reason strings);
        the methods EDI_REFERENCE / BLURRY_REFERENCE hold the reference images' PSNR / SSIM on
        the input views when the scene has ground truth.
    """
    config, pipeline, checkpoint, step = _load(Path(config_path))
    label = method or str(config.method_name)
    return evaluate_pipeline(
        pipeline, Path(output_dir), label, split=split, lpips_weights=lpips_weights, max_grids=max_grids,
        align_novel=align_novel, extra_notes=[f"Checkpoint {checkpoint} (step {step})."], novel_pose_fit=novel_pose_fit,
    )


__all__: List[str] = [
    "evaluate_run", "evaluate_pipeline", "input_views", "novel_views", "ViewGroup",
    "INPUT_SPLIT", "NOVEL_SPLIT", "NOVEL_UNFITTED_SPLIT", "NOVEL_ANCHORED_SPLIT", "INITIAL_POSES_SPLIT", "REFINED_POSES_SPLIT", "IMAGE_METRIC_KEYS", "POSE_METRIC_KEYS",
]  # fmt: skip

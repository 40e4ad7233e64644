"""The ``edygs-data`` dataparser: any supported scene folder -> nerfstudio DataparserOutputs.

A layout reader (edygs_ns.data.layouts) turns the folder into a neutral SceneRecord; this
module orients, centres and scales the poses the nerfstudio way (the transform is fitted once,
on all latent poses, and shared by every split), splits the cameras and fills the metadata
the EDyGS datamanager and model read:

========================  =====================================================================
``theta``, ``k``          contrast threshold (float), latents per blurry frame (int)
``color_space``           "linear" or "srgb": encoding of the stored pixels
``points3D_xyz/_rgb``     [P, 3] float32 / uint8 initial points, in the transformed frame
``event_maps``            float32 [n_blurry, k-1, H, W] (train split only); bin j of exposure b
                          is the signed event count between latents j and j+1 of b
``latent_to_pair``        long [N] (train split only): for camera i, the camera index of the
                          next latent of the same exposure in this split, else -1
``blurry_index``          long [N] exposure of each camera (-1 for novel views)
``latent_index``          long [N] position in the exposure (-1 for novel views and blurry frames)
``blurry_filenames``      the n_blurry blurry images, indexed by blurry_index
``gt_image_filenames``    sharp ground truth aligned with the cameras (only when it exists)
``gt_mask_filenames``     ground-truth motion masks aligned with the cameras (only when they exist)
``gt_covisible_filenames`` novel views: per pixel, how many training latents saw it (8-bit; simulator)
``gt_camera_to_worlds``   float32 [N, 3, 4] ground-truth poses, transformed like the cameras
``gt_units_scale``        float: length of one ground-truth unit in this frame (the dataparser
                          scale times the Sim(3) scale that moved the ground truth into the
                          estimated poses' frame); trajectory errors divide by it
``pose_source``           where the latent poses came from ("given", "colmap", ...)
========================  =====================================================================

Evaluation cameras show the sharp ground truth where the scene has it, else the EDI latents.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple, Type

import numpy as np
import torch
from nerfstudio.cameras import camera_utils
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.utils.rich_utils import CONSOLE
from tyro.conf import Suppress

from edygs_ns.data.layouts import read_scene
from edygs_ns.data.layouts.common import GT_ALIGNMENT_SCALE_NOTE, PROCESSED_LAYOUT, SceneRecord
from edygs_ns.io.images import UINT8_MAX
from edygs_ns.preprocess.triangulate import cached_points_at_poses
from edygs_ns.geometry import Intrinsics

#: Below this camera-centre extent (after centring) poses are not auto-scaled (it would blow up).
MIN_POSE_EXTENT = 1e-6
#: Index value for cameras that are not a latent of an exposure (novel views, blurry frames).
NOT_A_LATENT = -1


@dataclass
class EdygsDataParserConfig(DataParserConfig):
    """Reads EDyGS scenes: our processed layout, E2NeRF's synthetic and real layouts, EvDeblurNeRF scenes."""

    _target: Type = field(default_factory=lambda: EdygsDataParser)
    data: Path = Path("data/edygs/scene")
    """Scene folder."""
    layout: Literal["auto", "processed", "e2nerf-synthetic", "e2nerf-real", "evdeblurnerf"] = "auto"
    """Folder layout; "auto" detects it from the files present."""
    image_source: Literal["latent", "blurry"] = "latent"
    """Training images: the EDI latents, or the blurry frames (the baseline)."""
    eval_mode: Literal["novel", "interval", "all"] = "novel"
    """Eval split: ground-truth novel views, interval hold-out, or all latents."""
    eval_interval: int = 8
    """Blurry frames b with b % eval_interval == 0 are held out in "interval" mode."""
    orientation_method: Literal["pca", "up", "vertical", "none"] = "up"
    """How poses are rotated (nerfstudio's auto_orient_and_center_poses)."""
    center_method: Literal["poses", "focus", "none"] = "poses"
    """How poses are centred."""
    auto_scale_poses: bool = True
    """Scale the poses so camera centres fit in [-1, 1]."""
    scale_factor: float = 1.0
    """Extra scale applied to the poses (after auto scaling)."""
    scene_scale: float = 1.0
    """Half side of the scene box (in transformed units)."""
    initial_points: Literal["triangulated", "random"] = "triangulated"
    """Initial points of an E2NeRF / EvDeblurNeRF scene (docs/layouts.md)."""
    num_random_points: int = 20000
    """Points drawn uniformly in the scene box when the scene has no point cloud."""
    random_seed: Suppress[int] = 0
    """Seed of those random points."""
    theta: Optional[float] = None
    """Contrast threshold override; None: the scene's value (docs/layouts.md)."""
    color_space: Optional[Literal["linear", "srgb"]] = None
    """Pixel encoding override; None: the scene's value."""
    edi_clip_max: Suppress[float] = 1.0
    """Clip (linear intensity) of EDI latents computed for E2NeRF and EvDeblurNeRF layouts."""
    k: Optional[int] = None
    """Latents per blurry frame of an EvDeblurNeRF scene (None: 5)."""


@dataclass
class _SceneTransform:
    """Orientation [3, 4] and scale fitted on the latent poses."""

    matrix: torch.Tensor
    scale: float

    def poses(self, c2w: np.ndarray) -> torch.Tensor:
        """Apply to OpenGL c2w [N, 4, 4] -> float32 [N, 3, 4]."""
        out = self.matrix.double() @ torch.from_numpy(np.asarray(c2w, dtype=np.float64))
        out[:, :3, 3] *= self.scale
        return out.float()

    def points(self, xyz: np.ndarray) -> torch.Tensor:
        """Apply to points [P, 3] -> float32 [P, 3]."""
        pts = torch.from_numpy(np.asarray(xyz, dtype=np.float64))
        out = pts @ self.matrix[:, :3].double().T + self.matrix[:, 3].double()
        return (out * self.scale).float()


def _fit_transform(record: SceneRecord, config: EdygsDataParserConfig) -> _SceneTransform:
    poses = torch.from_numpy(record.latent_c2w.astype(np.float32))
    oriented, matrix = camera_utils.auto_orient_and_center_poses(
        poses, method=config.orientation_method, center_method=config.center_method
    )
    scale = 1.0
    extent = float(torch.max(torch.abs(oriented[:, :3, 3])))
    if config.auto_scale_poses:
        if extent > MIN_POSE_EXTENT:
            scale /= extent
        else:
            CONSOLE.log(f"[yellow]{record.root}: camera centres coincide; poses are not auto-scaled")
    return _SceneTransform(matrix=matrix.float(), scale=scale * config.scale_factor)


def _mean_pose(c2w: np.ndarray) -> np.ndarray:
    """Average of poses [M, 4, 4]: mean centre, rotation = the mean matrix projected onto SO(3)."""
    out = np.eye(4)
    u, _, vt = np.linalg.svd(c2w[:, :3, :3].mean(axis=0))
    fix = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    out[:3, :3] = u @ fix @ vt
    out[:3, 3] = c2w[:, :3, 3].mean(axis=0)
    return out


def _central_latents(k: int) -> Tuple[int, ...]:
    """Latent positions whose average is the exposure centre: the middle one, or the two middle ones."""
    return ((k - 1) // 2,) if k % 2 else (k // 2 - 1, k // 2)


def _cameras(intr: Intrinsics, c2w: torch.Tensor, times: np.ndarray) -> Cameras:
    return Cameras(
        camera_to_worlds=c2w,
        fx=float(intr.fl_x),
        fy=float(intr.fl_y),
        cx=float(intr.cx),
        cy=float(intr.cy),
        width=int(intr.width),
        height=int(intr.height),
        camera_type=CameraType.PERSPECTIVE,
        times=torch.as_tensor(np.asarray(times, dtype=np.float32)).reshape(-1, 1),
    )


class EdygsDataParser(DataParser):
    """Dataparser for EDyGS scenes (see the module docstring for the metadata it fills)."""

    config: EdygsDataParserConfig
    includes_time: bool = True

    def __init__(self, config: EdygsDataParserConfig):
        super().__init__(config=config)
        self._record: Optional[SceneRecord] = None
        self._transform: Optional[_SceneTransform] = None
        self._warned_fallback = False

    # -- scene, once per parser ---------------------------------------------------------------

    def scene(self) -> SceneRecord:
        """The scene record, read (and its caches built) on first use."""
        if self._record is None:
            cfg = self.config
            self._record = read_scene(
                Path(cfg.data), cfg.layout, theta=cfg.theta, color_space=cfg.color_space, clip_max=cfg.edi_clip_max,
                k=cfg.k,
            )
            if cfg.initial_points == "triangulated" and self._record.layout != PROCESSED_LAYOUT:
                self._triangulate(self._record)
            self._transform = _fit_transform(self._record, cfg)
            r = self._record
            CONSOLE.log(
                f"edygs-data: {r.root} ({r.layout}): {r.num_blurry} blurry frames, {r.num_latents} latents, k={r.k}, "
                f"{r.intrinsics.width}x{r.intrinsics.height}, poses {r.pose_source}"
                + (f", {len(r.novel)} novel views" if r.novel is not None else "")
            )
        return self._record

    def _triangulate(self, record: SceneRecord) -> None:
        """Give a scene without points those triangulated at its given poses (cached), or warn once
        that it starts from random points."""
        if record.points_xyz is not None or record.pose_source != "given":
            return
        points, line = cached_points_at_poses(record.root, record.latent_image_paths, record.latent_c2w,
                                              record.intrinsics)
        if points is None:
            CONSOLE.print(f"[yellow]warning[/]: {record.root}: no triangulated initial points ({line}); starting from "
                          f"{self.config.num_random_points:,} random points in the scene box", soft_wrap=True)
            return
        record.points_xyz, record.points_rgb = points.xyz.astype(np.float32), points.rgb
        record.notes = dict(record.notes or {}, initial_points=line)
        CONSOLE.log(f"edygs-data: {line}")

    def _eval_mode(self, record: SceneRecord) -> str:
        mode = self.config.eval_mode
        if mode == "novel" and record.novel is None:
            if not self._warned_fallback:
                CONSOLE.print(
                    f"[bold yellow]edygs-data: {record.root} has no ground-truth novel views; "
                    f"falling back to eval_mode='interval' (blurry frames b with b % {self.config.eval_interval} == 0 held out)"
                )
                self._warned_fallback = True
            return "interval"
        return mode

    def _latent_split(self, record: SceneRecord, split: str, mode: str) -> np.ndarray:
        """Indices of the latents in ``split``: all of them ("all", or training in "novel"), or by interval."""
        if mode in ("all", "novel"):
            return np.arange(record.num_latents)
        interval = self.config.eval_interval
        if interval < 1:
            raise ValueError(f"eval_interval must be >= 1, got {interval}")
        held_out = record.blurry_index % interval == 0
        if held_out.all() or not held_out.any():
            raise ValueError(
                f"{record.root}: eval_interval={interval} holds out {int(held_out.sum())} of {record.num_blurry} blurry "
                "frames; choose an interval that leaves both training and evaluation frames"
            )
        return np.flatnonzero(~held_out if split == "train" else held_out)

    # -- outputs --------------------------------------------------------------------------------

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs: Any) -> DataparserOutputs:
        record = self.scene()
        assert self._transform is not None
        mode = self._eval_mode(record)
        is_train = split == "train"
        if not is_train and mode == "novel":
            outputs = self._novel_outputs(record)
        elif is_train and self.config.image_source == "blurry":
            outputs = self._blurry_outputs(record, self._latent_split(record, split, mode))
        else:
            outputs = self._latent_outputs(record, self._latent_split(record, split, mode), is_train)
        if is_train:
            outputs.metadata["event_maps"] = torch.from_numpy(np.array(record.event_maps, dtype=np.float32))
        return outputs

    def _common_metadata(self, record: SceneRecord) -> Dict[str, Any]:
        xyz, rgb = self._points(record)
        return {
            "theta": float(record.theta),
            "k": int(record.k),
            "color_space": str(record.color_space),
            "points3D_xyz": xyz,
            "points3D_rgb": rgb,
            "blurry_filenames": list(record.blurry_image_paths),
            "pose_source": record.pose_source,
        }

    def _points(self, record: SceneRecord) -> Tuple[torch.Tensor, torch.Tensor]:
        assert self._transform is not None
        if record.points_xyz is not None and record.points_rgb is not None and len(record.points_xyz):
            return self._transform.points(record.points_xyz), torch.from_numpy(np.asarray(record.points_rgb, np.uint8))
        gen = torch.Generator().manual_seed(self.config.random_seed)
        s = self.config.scene_scale
        xyz = (torch.rand((self.config.num_random_points, 3), generator=gen) * 2.0 - 1.0) * s
        rgb = torch.randint(0, UINT8_MAX + 1, (self.config.num_random_points, 3), generator=gen, dtype=torch.uint8)
        return xyz, rgb

    def _finish(
        self, record: SceneRecord, cameras: Cameras, images: List[Path], metadata: Dict[str, Any]
    ) -> DataparserOutputs:
        assert self._transform is not None
        s = self.config.scene_scale
        return DataparserOutputs(
            image_filenames=images,
            cameras=cameras,
            scene_box=SceneBox(aabb=torch.tensor([[-s, -s, -s], [s, s, s]], dtype=torch.float32)),
            metadata=dict(self._common_metadata(record), **metadata),
            dataparser_transform=self._transform.matrix,
            dataparser_scale=self._transform.scale,
        )

    def _latent_outputs(self, record: SceneRecord, chosen: np.ndarray, is_train: bool) -> DataparserOutputs:
        assert self._transform is not None
        c2w = self._transform.poses(record.latent_c2w[chosen])
        cameras = _cameras(record.intrinsics, c2w, record.latent_times[chosen])
        has_gt = record.gt_image_paths is not None
        if is_train or not has_gt:
            images = [record.latent_image_paths[i] for i in chosen]
        else:
            images = [record.gt_image_paths[i] for i in chosen]  # type: ignore[index]
        blurry = record.blurry_index[chosen]
        latent = record.latent_index[chosen]
        meta: Dict[str, Any] = {
            "blurry_index": torch.from_numpy(blurry.astype(np.int64)),
            "latent_index": torch.from_numpy(latent.astype(np.int64)),
        }
        if is_train:
            meta["latent_to_pair"] = _next_latent(blurry, latent)
        if has_gt:
            meta["gt_image_filenames"] = [record.gt_image_paths[i] for i in chosen]  # type: ignore[index]
        if record.gt_mask_paths is not None:
            meta["gt_mask_filenames"] = [record.gt_mask_paths[i] for i in chosen]
        if record.gt_c2w is not None:
            meta["gt_camera_to_worlds"] = self._transform.poses(record.gt_c2w[chosen])
            gt_scale = float((record.notes or {}).get(GT_ALIGNMENT_SCALE_NOTE, 1.0))
            meta["gt_units_scale"] = float(self._transform.scale) * gt_scale
        return self._finish(record, cameras, images, meta)

    def _novel_outputs(self, record: SceneRecord) -> DataparserOutputs:
        assert self._transform is not None and record.novel is not None
        novel = record.novel
        c2w = self._transform.poses(novel.camera_to_worlds)
        none = torch.full((len(novel),), NOT_A_LATENT, dtype=torch.long)
        meta: Dict[str, Any] = {
            "blurry_index": none,
            "latent_index": none.clone(),
            "gt_image_filenames": list(novel.image_paths),
            "gt_camera_to_worlds": c2w.clone(),
        }
        if novel.mask_paths is not None:
            meta["gt_mask_filenames"] = list(novel.mask_paths)
        if novel.covisible_paths is not None:
            meta["gt_covisible_filenames"] = list(novel.covisible_paths)
        return self._finish(record, _cameras(novel.intrinsics, c2w, novel.times), list(novel.image_paths), meta)

    def _blurry_outputs(self, record: SceneRecord, train_latents: np.ndarray) -> DataparserOutputs:
        """One camera per blurry frame with training latents, at the exposure-centre pose and time."""
        assert self._transform is not None
        central = _central_latents(record.k)
        poses, times, frames = [], [], []
        for b in np.unique(record.blurry_index[train_latents]):
            mine = train_latents[record.blurry_index[train_latents] == b]
            # The latents nearest the exposure centre that this frame has (all, normally).
            dist = np.abs(record.latent_index[mine] - np.mean(central))
            picked = mine[dist == dist.min()]
            poses.append(_mean_pose(record.latent_c2w[picked]))
            times.append(float(record.latent_times[picked].mean()))
            frames.append(int(b))
        cameras = _cameras(record.intrinsics, self._transform.poses(np.stack(poses)), np.array(times))
        meta = {
            "blurry_index": torch.tensor(frames, dtype=torch.long),
            "latent_index": torch.full((len(frames),), NOT_A_LATENT, dtype=torch.long),
            "latent_to_pair": torch.full((len(frames),), NOT_A_LATENT, dtype=torch.long),
        }
        return self._finish(record, cameras, [record.blurry_image_paths[b] for b in frames], meta)


def _next_latent(blurry: np.ndarray, latent: np.ndarray) -> torch.Tensor:
    """For each camera, the index of the camera holding the next latent of its exposure, or -1."""
    position = {(int(b), int(j)): i for i, (b, j) in enumerate(zip(blurry, latent))}
    nxt = [position.get((int(b), int(j) + 1), NOT_A_LATENT) for b, j in zip(blurry, latent)]
    return torch.tensor(nxt, dtype=torch.long)

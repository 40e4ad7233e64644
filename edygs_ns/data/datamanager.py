"""The EDyGS datamanager: serves pairs of consecutive latent frames with the events between them.

Every image is loaded once (nerfstudio's full-image caching); the event maps of the whole
scene live in memory as one tensor on the training device. A training step draws, without
replacement from a shuffled list refilled each epoch, one pair (i, i+1) of consecutive latents
of the same exposure and returns both cameras, both images and the signed event count between
them. Nothing is read from disk or re-binned per iteration.

Batches (C cameras, H x W pixels)::

    pairs      cameras [2]; {"image": float32 [2, H, W, 3] in [0, 1], "event_map": float32 [H, W],
               "image_idx": long [2], "blurry": float32 [1, H, W, 3] in [0, 1], the pair's blurry frame}
    singles    cameras [1]; {"image": float32 [1, H, W, 3], "image_idx": long [1]}
               (pair_events=False, or the blurry-input baseline)
    eval       cameras [1]; {"image": float32 [H, W, 3], "image_idx": int, "motion_mask": float32 [H, W, 1]
               motion mask (1 = dynamic), only when the scene has ground-truth masks}

Training cameras carry metadata["cam_idx"]: their train index (long [2, 1] for a pair, so that
slicing one camera out keeps it; an int for a single camera, as nerfstudio sets it).
"""

from __future__ import annotations

import random
from copy import deepcopy
from dataclasses import dataclass, field
from functools import cached_property
from typing import Dict, List, Literal, Optional, Set, Tuple, Type, Union

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig
from nerfstudio.utils.rich_utils import CONSOLE, get_progress
from PIL import Image
from tyro.conf import Suppress

from edygs_ns.cuda_setup import require_device
from edygs_ns.data.dataparser import EdygsDataParserConfig
from edygs_ns.io.images import UINT8_MAX

#: Metadata entries too large to deep-copy into nerfstudio's InputDataset.
HEAVY_METADATA_KEYS = ("event_maps",)
#: Cameras in a training pair.
PAIR_SIZE = 2


@dataclass
class EdygsDataManagerConfig(FullImageDatamanagerConfig):
    """Full-image datamanager that pairs consecutive latents with their events. The ``Suppress``
    fields, hidden from ``ns-train --help``, are nerfstudio's that have no effect on a
    FullImageDatamanager."""

    _target: Type = field(default_factory=lambda: EdygsDataManager)
    dataparser: EdygsDataParserConfig = field(default_factory=EdygsDataParserConfig)
    """The EDyGS dataparser (its metadata carries the event maps and latent pairing)."""
    masks_on_gpu: Suppress[bool] = False
    images_on_gpu: Suppress[bool] = False
    eval_num_images_to_sample_from: Suppress[int] = -1
    eval_num_times_to_repeat_images: Suppress[int] = -1
    eval_image_indices: Suppress[Optional[Tuple[int, ...]]] = (0,)
    cache_images: Literal["cpu", "gpu"] = "cpu"
    """Where decoded images are cached ("cpu": pinned when CUDA exists)."""
    max_thread_workers: Suppress[Optional[int]] = None
    pair_events: bool = True
    """Serve pairs of latents and their events (False: one camera per step)."""


class EdygsDataManager(FullImageDatamanager):
    """Serves latent pairs plus their event maps for training and sharp views for evaluation."""

    config: EdygsDataManagerConfig

    def __init__(
        self,
        config: EdygsDataManagerConfig,
        device: Union[torch.device, str] = "cpu",
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        **kwargs,
    ):
        require_device(device)
        super().__init__(
            config=config, device=device, test_mode=test_mode, world_size=world_size, local_rank=local_rank, **kwargs
        )
        self.includes_time = True
        meta = self.train_dataparser_outputs.metadata
        for key in ("event_maps", "latent_to_pair", "blurry_index", "latent_index"):
            if key not in meta:
                raise ValueError(f"EdygsDataManager: dataparser metadata lacks {key!r}; use the edygs-data dataparser")
        self.train_cameras = self.train_dataset.cameras
        self.blurry_index: torch.Tensor = meta["blurry_index"]
        self.latent_index: torch.Tensor = meta["latent_index"]
        self.pairs: List[Tuple[int, int]] = [(i, int(n)) for i, n in enumerate(meta["latent_to_pair"].tolist()) if n >= 0]
        # what a training step needs, ready where it is used: the exposure and place of every
        # latent on the host (the pair is drawn there), the pairs' indices and the cameras on the
        # training device, so a step uploads nothing but its images
        self._blurry_of: List[int] = self.blurry_index.tolist()
        self._latent_of: List[int] = self.latent_index.tolist()
        self._pair_row: Dict[Tuple[int, int], int] = {pair: row for row, pair in enumerate(self.pairs)}
        self._pair_indices = torch.tensor(self.pairs, dtype=torch.long).reshape(-1, PAIR_SIZE).to(self.device)
        self._device_cameras = self.train_cameras.to(self.device)
        image_source = getattr(self.dataparser.config, "image_source", "latent")
        self.serves_pairs = bool(config.pair_events and image_source == "latent")
        self.event_maps: Optional[torch.Tensor] = None
        self.blurry_frames: List[torch.Tensor] = []
        if self.serves_pairs:
            if not self.pairs:
                raise ValueError(f"{config.dataparser.data}: no two consecutive latents of one exposure in the training split")
            if config.camera_res_scale_factor != 1.0:
                raise ValueError("pair_events needs camera_res_scale_factor=1 (event maps are not resampled)")
            self.event_maps = meta["event_maps"].to(device=self.device, dtype=torch.float32)
            self.blurry_frames = self._load_blurry(meta.get("blurry_filenames") or [])
        self._pair_rng = random.Random(config.train_cameras_sampling_seed)
        times = self.train_cameras.times
        self._train_times: List[float] = times.reshape(-1).tolist() if times is not None else [0.0] * len(self.train_cameras)
        self.time_window: Optional[Tuple[float, float]] = None
        self._window_pairs: Optional[Set[Tuple[int, int]]] = None  # pairs inside time_window
        self.unseen_pairs: List[Tuple[int, int]] = self._shuffled_pairs()

    # -- setup ----------------------------------------------------------------------------------

    def create_train_dataset(self):
        """The parent's dataset, built without deep-copying the event maps into it."""
        meta = self.train_dataparser_outputs.metadata
        heavy = {key: meta.pop(key) for key in HEAVY_METADATA_KEYS if key in meta}
        try:
            return super().create_train_dataset()
        finally:
            meta.update(heavy)

    def _load_images(self, split: Literal["train", "eval"], cache_images_device: Literal["cpu", "gpu"]) -> List[Dict]:
        """Decode every image of a split once (our cameras are undistorted pinholes).

        Images go to the training device for cache_images="gpu"; on the CPU they are pinned only
        when CUDA exists (pinning needs a CUDA driver).
        """
        dataset = self.train_dataset if split == "train" else self.eval_dataset
        cached = []
        with get_progress(f"Caching {split} images") as progress:
            for idx in progress.track(range(len(dataset)), total=len(dataset)):
                try:
                    data = dataset.get_data(idx, image_type=self.config.cache_images_type)
                except (OSError, SyntaxError) as err:  # PIL: truncated or corrupt image files
                    raise ValueError(f"{dataset.image_filenames[idx]}: cannot decode the image ({err}); "
                                     "rewrite it (run edygs-process again for a processed scene)") from None
                height, width = int(dataset.cameras.height[idx]), int(dataset.cameras.width[idx])
                if tuple(data["image"].shape[:2]) != (height, width):
                    raise ValueError(
                        f"{dataset.image_filenames[idx]}: image is {tuple(data['image'].shape[:2])} (H, W) but its "
                        f"camera is {(height, width)}"
                    )
                if cache_images_device == "gpu":
                    data["image"] = data["image"].to(self.device)
                elif torch.cuda.is_available():
                    data["image"] = data["image"].pin_memory()
                cached.append(data)
        return cached

    def _load_blurry(self, files: List) -> List[torch.Tensor]:
        """Every blurry frame once, float32 [H, W, 3] in [0, 1] on the training device (the blur
        loss's targets); they must have the training images' size."""
        height, width = int(self.train_cameras.height[0]), int(self.train_cameras.width[0])
        frames = []
        for path in files:
            try:
                with Image.open(path) as img:
                    if (img.height, img.width) != (height, width):
                        raise ValueError(f"{path}: blurry frame is {(img.height, img.width)} (H, W) but the latents are {(height, width)}")
                    rgb = np.asarray(img.convert("RGB"), dtype=np.float32) / UINT8_MAX
            except (OSError, SyntaxError) as err:  # PIL: truncated or corrupt image files
                raise ValueError(f"{path}: cannot decode the blurry frame ({err})") from None
            frames.append(torch.from_numpy(rgb).to(self.device))
        return frames

    # -- training -------------------------------------------------------------------------------

    def _shuffled_pairs(self) -> List[Tuple[int, int]]:
        order = list(self.pairs)
        self._pair_rng.shuffle(order)
        return order

    def set_time_window(self, window: Optional[Tuple[float, float]]) -> None:
        """Draw training pairs only with both normalised times in [lo, hi] (None: the whole clip).

        A window that holds no training pair serves the pair nearest its centre."""
        if window == self.time_window:
            return
        self.time_window = window
        if window is None:
            self._window_pairs = None
            return
        lo, hi = window
        times = self._train_times
        inside = {p for p in self.pairs if lo <= times[p[0]] <= hi and lo <= times[p[1]] <= hi}
        if not inside:
            centre = 0.5 * (lo + hi)
            inside = {min(self.pairs, key=lambda p: abs(0.5 * (times[p[0]] + times[p[1]]) - centre))}
        self._window_pairs = inside

    def next_pair(self) -> Tuple[int, int]:
        """The next (i, i+1) train-camera pair of this epoch inside the time window; a new shuffled
        epoch starts when all were served (pairs outside the window are passed over for this epoch)."""
        while True:
            pair = self.unseen_pairs.pop(0)
            if not self.unseen_pairs:
                self.unseen_pairs = self._shuffled_pairs()
            if self._window_pairs is None or pair in self._window_pairs:
                return pair

    def train_image(self, idx: int) -> torch.Tensor:
        """Training image ``idx`` as float32 [H, W, 3|4] in [0, 1] on the training device."""
        cached = self.cached_train[idx]["image"]
        image = cached.to(self.device, non_blocking=cached.is_pinned())  # pinned: an asynchronous copy
        return image.float() / UINT8_MAX if image.dtype == torch.uint8 else image

    def next_train(self, step: int) -> Tuple[Cameras, Dict]:
        """A pair of consecutive latents with their event map, or a single camera (see module docstring)."""
        if not self.serves_pairs:
            camera, data = super().next_train(step)
            idx = int(camera.metadata["cam_idx"])  # type: ignore[index]
            return camera, {"image": self.train_image(idx)[None], "image_idx": torch.tensor([idx], dtype=torch.long)}
        assert self.event_maps is not None
        first, second = self.next_pair()
        indices = self._pair_indices[self._pair_row[(first, second)]]  # long [2] on the training device
        cameras = self._device_cameras[indices]
        cameras.metadata = {"cam_idx": indices.reshape(PAIR_SIZE, 1)}
        batch = {
            "image": torch.stack([self.train_image(first), self.train_image(second)]),
            "event_map": self.event_maps[self._blurry_of[first], self._latent_of[first]],
            "image_idx": indices,
        }
        exposure = self._blurry_of[first]
        if 0 <= exposure < len(self.blurry_frames):
            batch["blurry"] = self.blurry_frames[exposure][None]
        return cameras, batch

    # -- evaluation -----------------------------------------------------------------------------

    @cached_property
    def eval_masks(self) -> Optional[List[torch.Tensor]]:
        """Ground-truth motion masks [H, W, 1] float in [0, 1] aligned with the eval cameras, or None."""
        files = self.eval_dataset.metadata.get("gt_mask_filenames")
        if not files:
            return None
        masks = []
        for idx, path in enumerate(files):
            size = (int(self.eval_dataset.cameras.width[idx]), int(self.eval_dataset.cameras.height[idx]))
            with Image.open(path) as img:
                grey = img.convert("L")
                if grey.size != size:
                    grey = grey.resize(size, Image.NEAREST)
                masks.append(torch.from_numpy(np.asarray(grey, dtype=np.float32) / UINT8_MAX)[..., None])
        CONSOLE.log(f"Loaded {len(masks)} ground-truth motion masks for evaluation")
        return masks

    def _with_mask(self, idx: int, data: Dict) -> Dict:
        masks = self.eval_masks
        if masks is not None:
            data["motion_mask"] = masks[idx].to(self.device)
        return data

    def next_eval_image(self, step: int) -> Tuple[Cameras, Dict]:
        """One evaluation camera [1] with its sharp image and (when known) its motion mask."""
        camera, data = super().next_eval_image(step)
        return camera, self._with_mask(int(data["image_idx"]), data)

    def next_eval(self, step: int) -> Tuple[Cameras, Dict]:
        """Same as next_eval_image."""
        return self.next_eval_image(step)

    @property
    def fixed_indices_eval_dataloader(self) -> List[Tuple[Cameras, Dict]]:
        """Every evaluation (camera [1], data) pair, with masks when known."""
        cameras = deepcopy(self.eval_dataset.cameras).to(self.device)
        out = []
        for idx, cached in enumerate(self.cached_eval):
            data = dict(cached, image=cached["image"].to(self.device))
            out.append((cameras[idx : idx + 1], self._with_mask(idx, data)))
        return out

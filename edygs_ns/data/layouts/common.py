"""The neutral scene description every layout reader produces, and helpers the readers share.

A layout reader turns one folder into a :class:`SceneRecord`: intrinsics, one entry per latent
(sharp) frame with its pose, time and image, the blurry frames, the event maps, optional points
and optional ground truth. The dataparser converts a SceneRecord into nerfstudio's
DataparserOutputs; nothing downstream knows which layout the folder had.

Poses are camera-to-world [N, 4, 4] float64 in the OpenGL camera convention (x right, y up,
camera looks down -z), in the layout's own world frame (no nerfstudio orientation applied).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from edygs_ns.events.edi import EdiConfig
from edygs_ns.geometry import POSE_SIZE, Intrinsics

#: The layout names a reader can produce.
#: The layout edygs-process writes; the others are read directly from their authors' folders.
PROCESSED_LAYOUT = "processed"
LAYOUT_NAMES: Tuple[str, ...] = (PROCESSED_LAYOUT, "e2nerf-synthetic", "e2nerf-real", "evdeblurnerf")
#: Pixel encoding of the layouts read directly (E2NeRF and EvDeblurNeRF data are linear).
DEFAULT_COLOR_SPACE = "linear"
#: Key of SceneRecord.notes holding the scale of the Sim(3) that moved the ground-truth poses
#: into the estimated poses' frame (estimated units per ground-truth unit).
GT_ALIGNMENT_SCALE_NOTE = "gt_alignment_scale"


@dataclass
class ViewSet:
    """Cameras with sharp ground-truth images (e.g. the novel views kept for evaluation).

    Attributes:
        intrinsics: shared pinhole intrinsics of these views.
        camera_to_worlds: [V, 4, 4] OpenGL camera-to-world, in the scene's world frame.
        times: [V] normalised time in [0, 1] on the same clock as the latent frames.
        image_paths: V sharp images.
        mask_paths: V motion masks (white = dynamic), or None.
        covisible_paths: V 8-bit maps of how many training latents saw each pixel, or None.
    """

    intrinsics: Intrinsics
    camera_to_worlds: np.ndarray
    times: np.ndarray
    image_paths: List[Path]
    mask_paths: Optional[List[Path]] = None
    covisible_paths: Optional[List[Path]] = None

    def __len__(self) -> int:
        return len(self.image_paths)


@dataclass
class SceneRecord:
    """One scene, independent of the folder layout it was read from.

    N latent frames, n blurry frames, k latents per blurry frame, H x W pixels.

    Attributes:
        root: the scene folder.
        layout: which reader produced this record (one of LAYOUT_NAMES).
        intrinsics: pinhole intrinsics of the latent and blurry frames.
        k: latent frames per blurry frame (k - 1 event bins per exposure).
        theta: event contrast threshold (log-intensity change per event).
        color_space: encoding of the stored pixels, "linear" or "srgb".
        latent_c2w: [N, 4, 4] OpenGL camera-to-world of every latent frame (training poses).
        latent_times: [N] float normalised time in [0, 1] (first latent 0, last 1).
        blurry_index: [N] int64 exposure each latent belongs to, in [0, n).
        latent_index: [N] int64 position of the latent inside its exposure, in [0, k).
        latent_image_paths: N latent (EDI) images.
        blurry_image_paths: n blurry images (RGB), indexed by blurry_index.
        event_maps: [n, k-1, H, W] float32 signed event counts; bin j of exposure b spans
            latent j to latent j+1 of that exposure. May be a read-only memory map.
        pose_source: where the latent poses came from ("given", "colmap", ...).
        points_xyz: [P, 3] float32 initial points in the world frame, or None.
        points_rgb: [P, 3] uint8 colours of the points, or None.
        gt_image_paths: N sharp ground-truth images aligned with the latents, or None.
        gt_mask_paths: N ground-truth motion masks aligned with the latents, or None.
        gt_c2w: [N, 4, 4] ground-truth poses of the latents in the same world frame as
            latent_c2w, or None.
        novel: held-out novel views with sharp images, or None.
        notes: free-form facts about how the record was built (logged, not interpreted).
    """

    root: Path
    layout: str
    intrinsics: Intrinsics
    k: int
    theta: float
    color_space: str
    latent_c2w: np.ndarray
    latent_times: np.ndarray
    blurry_index: np.ndarray
    latent_index: np.ndarray
    latent_image_paths: List[Path]
    blurry_image_paths: List[Path]
    event_maps: np.ndarray
    pose_source: str = "given"
    points_xyz: Optional[np.ndarray] = None
    points_rgb: Optional[np.ndarray] = None
    gt_image_paths: Optional[List[Path]] = None
    gt_mask_paths: Optional[List[Path]] = None
    gt_c2w: Optional[np.ndarray] = None
    novel: Optional[ViewSet] = None
    notes: Optional[Dict[str, Any]] = None

    @property
    def num_latents(self) -> int:
        return int(len(self.latent_image_paths))

    @property
    def num_blurry(self) -> int:
        return int(len(self.blurry_image_paths))

    def check(self) -> None:
        """Check that every per-latent array has N entries and indices are in range.

        Raises:
            ValueError: naming the scene folder and the inconsistent field.
        """
        n = self.num_latents
        where = f"{self.root} ({self.layout})"
        per_latent = {
            "latent_c2w": self.latent_c2w,
            "latent_times": self.latent_times,
            "blurry_index": self.blurry_index,
            "latent_index": self.latent_index,
        }
        for name, values in per_latent.items():
            if len(values) != n:
                raise ValueError(f"{where}: {name} has {len(values)} entries for {n} latent frames")
        if self.latent_c2w.shape[1:] != (POSE_SIZE, POSE_SIZE):
            raise ValueError(f"{where}: latent poses have shape {self.latent_c2w.shape}, expected [N, 4, 4]")
        for name in ("gt_image_paths", "gt_mask_paths", "gt_c2w"):
            values = getattr(self, name)
            if values is not None and len(values) != n:
                raise ValueError(f"{where}: {name} has {len(values)} entries for {n} latent frames")
        if n and (self.blurry_index.min() < 0 or self.blurry_index.max() >= self.num_blurry):
            raise ValueError(f"{where}: blurry_index outside [0, {self.num_blurry}) blurry frames")
        if n and (self.latent_index.min() < 0 or self.latent_index.max() >= self.k):
            raise ValueError(f"{where}: latent_index outside [0, k={self.k})")
        if n and (self.latent_times.min() < 0.0 or self.latent_times.max() > 1.0):
            raise ValueError(f"{where}: latent times leave [0, 1]: [{self.latent_times.min()}, {self.latent_times.max()}]")
        expected = (self.num_blurry, self.k - 1, self.intrinsics.height, self.intrinsics.width)
        if tuple(self.event_maps.shape) != expected:
            raise ValueError(
                f"{where}: event maps have shape {tuple(self.event_maps.shape)}, expected {expected} "
                "[blurry frames, k-1, H, W]"
            )


def uniform_latent_times(n_blurry: int, k: int) -> np.ndarray:
    """Normalised times [n * k] for layouts without timestamps.

    Exposures are assumed equally long and back to back with one bin between them, so latent
    j of exposure b sits at slot b * k + j and all latents are evenly spaced over [0, 1].
    """
    slots = np.arange(n_blurry * k, dtype=np.float64)
    return slots / max(n_blurry * k - 1, 1)


def latent_times_from_fractions(fractions: np.ndarray) -> np.ndarray:
    """Normalised times [n * k] of latents placed at fractions of their exposures.

    As :func:`uniform_latent_times` (equally long exposures, back to back, one bin between
    them), but latent j of exposure b sits at fractions[b, j] of its exposure: slot
    b * k + fractions[b, j] * (k - 1). Fractions j / (k - 1) give uniform_latent_times.

    Args:
        fractions: [n, k] in [0, 1], increasing along k, first 0 and last 1.

    Returns:
        [n * k] float64 in [0, 1].
    """
    fractions = np.asarray(fractions, dtype=np.float64)
    n, k = fractions.shape
    slots = np.arange(n, dtype=np.float64)[:, None] * k + fractions * (k - 1)
    return (slots / max(n * k - 1, 1)).reshape(-1)


def nearest_times(query_c2w: np.ndarray, latent_c2w: np.ndarray, latent_times: np.ndarray) -> np.ndarray:
    """For each query pose, the time of the latent whose camera centre is nearest.

    Used for novel views of layouts that carry no time for them (static E2NeRF scenes).

    Args:
        query_c2w: [V, 4, 4] poses.
        latent_c2w: [N, 4, 4] poses of the latents.
        latent_times: [N] their normalised times.

    Returns:
        [V] float64 times.
    """
    diff = query_c2w[:, None, :3, 3] - latent_c2w[None, :, :3, 3]
    nearest = np.argmin((diff**2).sum(axis=-1), axis=1)
    return latent_times[nearest].astype(np.float64)


def latent_grid(n_blurry: int, k: int) -> Tuple[np.ndarray, np.ndarray]:
    """(blurry_index, latent_index) [n * k] int64 for every latent of n exposures, in time order."""
    blurry = np.repeat(np.arange(n_blurry, dtype=np.int64), k)
    latent = np.tile(np.arange(k, dtype=np.int64), n_blurry)
    return blurry, latent


def layout_edi_config(
    k: int, theta: Optional[float], default_theta: float, color_space: Optional[str], clip_max: float
) -> EdiConfig:
    """EDI settings of a layout read directly: the given Θ and encoding, else the layout's defaults
    (Θ ``default_theta``, pixels "linear")."""
    return EdiConfig(
        k=k,
        theta=float(theta if theta is not None else default_theta),
        color_space=color_space or DEFAULT_COLOR_SPACE,  # type: ignore[arg-type]
        clip_max=clip_max,
    )

"""Layout ``e2nerf-synthetic``: E2NeRF's synthetic (Blender-style) scenes read directly.

The folder is parsed by :mod:`edygs_ns.preprocess.e2nerf` (the reader ``edygs-process --e2nerf``
uses too, which documents the sub-frame convention: latents at sub-frames 0, 5, 9, 13, 17); here
it becomes a SceneRecord. k = bins + 1 of the event file.

Pixels: E2NeRF's synthetic config sets ``white_bkgd = False``, so the stored RGB is kept and alpha
dropped, for the blurry and the test images (converted once and cached as RGB). EDI latents are
computed once and cached; Θ 0.2 by default (ours; E2NeRF's 0.3 is for its real data). The scenes
are static and carry no timestamps: exposures are placed back to back on [0, 1] and each latent at
its sub-frame's instant within its exposure (common.latent_times_from_fractions); each test view
gets the time of the training latent whose camera centre is nearest.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from edygs_ns.data.layouts.common import (
    SceneRecord, ViewSet, latent_grid, latent_times_from_fractions, layout_edi_config, nearest_times,
)
from edygs_ns.io.images import image_size
from edygs_ns.preprocess import e2nerf
from edygs_ns.preprocess.cache import cached_edi_latents, cached_events_pt, cached_rgb_images

#: Background that transparent pixels are composited on: None, i.e. alpha dropped and the
#: stored RGB kept (E2NeRF's synthetic config has white_bkgd = False).
BACKGROUND = None
#: Default contrast threshold for E2NeRF synthetic data.
DEFAULT_THETA = e2nerf.SYNTHETIC_THETA


def _read_test_views(scene: e2nerf.SyntheticScene, latent_c2w: np.ndarray, latent_times: np.ndarray) -> Optional[ViewSet]:
    """The sharp test views (alpha dropped as E2NeRF does, cached), or None if the scene has none."""
    found = scene.test_views()
    if found is None:
        return None
    meta, source, images, c2w = found
    height, width = image_size(images[0])
    rgb = cached_rgb_images(scene.root, "test_rgb", images, [p.name for p in images], background=BACKGROUND)
    return ViewSet(
        intrinsics=e2nerf.blender_intrinsics(meta, source, height, width),
        camera_to_worlds=c2w,
        times=nearest_times(c2w, latent_c2w, latent_times),
        image_paths=rgb,
        mask_paths=None,
    )


def read_e2nerf_synthetic(
    root: Path, theta: Optional[float] = None, color_space: Optional[str] = None, clip_max: float = 1.0
) -> SceneRecord:
    """Read an E2NeRF synthetic scene, computing (once) and caching its EDI latents.

    Args:
        root: the scene folder.
        theta: contrast threshold for EDI (default DEFAULT_THETA).
        color_space: encoding of the pixels (default "linear", as E2NeRF treats them).
        clip_max: EDI latents are clipped to [0, clip_max] in linear intensity.

    Raises:
        FileNotFoundError: a required file or folder is missing.
        ValueError: malformed JSON, or the event file disagrees with the images (names the file
            and both shapes).
    """
    scene = e2nerf.read_synthetic(root)
    originals = scene.image_paths
    height, width = image_size(originals[0])
    event_maps = cached_events_pt(scene.events_path, len(originals), height, width, root)
    k = int(event_maps.shape[1]) + 1
    latent_c2w, fractions = scene.latent_poses(k)
    latent_c2w = latent_c2w.reshape(-1, 4, 4)
    blurry_rgb = cached_rgb_images(root, "train_rgb", originals, [p.name for p in originals], background=BACKGROUND)
    edi = layout_edi_config(k, theta, DEFAULT_THETA, color_space, clip_max)
    latents = cached_edi_latents(root, blurry_rgb, event_maps, edi, sources=[scene.events_path] + originals)
    blurry_index, latent_index = latent_grid(len(originals), k)
    times = latent_times_from_fractions(fractions)
    record = SceneRecord(
        root=root,
        layout="e2nerf-synthetic",
        intrinsics=scene.intrinsics(height, width),
        k=k,
        theta=edi.theta,
        color_space=edi.color_space,
        latent_c2w=latent_c2w,
        latent_times=times,
        blurry_index=blurry_index,
        latent_index=latent_index,
        latent_image_paths=[p for row in latents for p in row],
        blurry_image_paths=blurry_rgb,
        event_maps=event_maps,
        pose_source="given",
        novel=_read_test_views(scene, latent_c2w, times),
        notes={"background": "none (alpha dropped, as E2NeRF's white_bkgd = False)",
               "frame_numbers": list(scene.numbers), "events_file": scene.events_path.name},
    )
    record.check()
    return record

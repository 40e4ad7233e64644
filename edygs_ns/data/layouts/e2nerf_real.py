"""Layout ``e2nerf-real``: E2NeRF's real (LLFF-style, DAVIS346) scenes read directly.

The folder is parsed by :mod:`edygs_ns.preprocess.e2nerf` (the reader ``edygs-process --e2nerf``
uses too); here it becomes a SceneRecord. k = bins + 1 of the event file, and poses_bounds.npy
holds one row per latent. EDI (Θ = 0.3 by default, E2NeRF's EDI.py) runs once and is cached.
There is no ground truth, and the files carry no timestamps: latents are evenly spaced over
[0, 1] (exposures back to back), which matches E2NeRF's equally long 25.001 ms bins.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from edygs_ns.data.layouts.common import SceneRecord, latent_grid, uniform_latent_times, layout_edi_config
from edygs_ns.io.images import image_size
from edygs_ns.preprocess import e2nerf
from edygs_ns.preprocess.cache import cached_edi_latents, cached_events_pt

#: Default contrast threshold: the Θ of E2NeRF's EDI.py.
DEFAULT_THETA = e2nerf.REAL_THETA


def read_e2nerf_real(
    root: Path, theta: Optional[float] = None, color_space: Optional[str] = None, clip_max: float = 1.0
) -> SceneRecord:
    """Read an E2NeRF real scene, computing (once) and caching its EDI latents.

    Args:
        root: the scene folder.
        theta: contrast threshold for EDI (default DEFAULT_THETA, 0.3 as E2NeRF's EDI).
        color_space: encoding of the pixels (default "linear").
        clip_max: EDI latents are clipped to [0, clip_max] in linear intensity.

    Raises:
        FileNotFoundError: a required file or folder is missing.
        ValueError: poses_bounds.npy or the event file disagree with the images (names the file
            and both shapes).
    """
    images = e2nerf.real_images(root)
    height, width = image_size(images[0])
    events = e2nerf.events_file(root)
    event_maps = cached_events_pt(events, len(images), height, width, root)
    k = int(event_maps.shape[1]) + 1
    scene = e2nerf.read_real(root, k, height, width, f"k={k} from {events.name}'s {k - 1} bins")
    edi = layout_edi_config(k, theta, DEFAULT_THETA, color_space, clip_max)
    latents = cached_edi_latents(root, images, event_maps, edi, sources=[events])
    blurry_index, latent_index = latent_grid(len(images), k)
    record = SceneRecord(
        root=root,
        layout="e2nerf-real",
        intrinsics=scene.intrinsics,
        k=k,
        theta=edi.theta,
        color_space=edi.color_space,
        latent_c2w=scene.c2w.reshape(-1, 4, 4),
        latent_times=uniform_latent_times(len(images), k),
        blurry_index=blurry_index,
        latent_index=latent_index,
        latent_image_paths=[p for row in latents for p in row],
        blurry_image_paths=images,
        event_maps=event_maps,
        pose_source="given",
        notes={"theta_source": "given" if theta is not None else "E2NeRF's EDI.py (real data)",
               "event_bins": f"E2NeRF's fixed {e2nerf.BIN_US} µs windows from each exposure start",
               "events_file": events.name},
    )
    record.check()
    return record

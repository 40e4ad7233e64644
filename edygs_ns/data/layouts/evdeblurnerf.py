"""Layout ``evdeblurnerf``: EvDeblurNeRF scenes read directly (the folder is parsed by
:mod:`edygs_ns.preprocess.evdeblurnerf`, the reader ``edygs-process --evdeblurnerf`` uses too).

The events are binned between the k latent instants of every blurry exposure and EDI runs once;
both are cached under the scene (:mod:`edygs_ns.preprocess.cache`). Sharp views become the novel
views (ground truth), at their own instant; normalised times span the first to the last latent.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import numpy as np

from edygs_ns.data.layouts.common import SceneRecord, ViewSet, latent_grid, layout_edi_config
from edygs_ns.events.accumulate import check_event_coverage, exposure_bins, latent_times_us
from edygs_ns.events.exposures import Exposure
from edygs_ns.preprocess.cache import EVENT_MAPS_FILE, CacheFolder, cached_edi_latents, check_event_maps_shape
from edygs_ns.preprocess.evdeblurnerf import (
    DEFAULT_COORDINATES,
    EVENTS_FILE,
    TIMESTAMPS_FILE,
    EvDeblurNeRFScene,
    read_evdeblurnerf_folder,
)

DEFAULT_K = 5
#: Layout name in SceneRecord.layout and the dataparser's ``layout`` option.
LAYOUT_NAME = "evdeblurnerf"



def _cached_event_maps(scene: EvDeblurNeRFScene, exposures: List[Exposure], k: int) -> np.ndarray:
    """[n, k-1, H, W] event bins of every exposure, computed once and cached under the scene."""
    from nerfstudio.utils.rich_utils import CONSOLE

    params = {"format": "evdeblurnerf-events.h5", "k": k, "events_unit": scene.events_unit,
              "rectified": scene.rectified_events, "coordinates": scene.coordinates, "exposures": [[e.start_us, e.end_us] for e in exposures]}
    cache = CacheFolder(scene.root, "event_maps", params, [scene.events_path])
    cached = cache.path / EVENT_MAPS_FILE
    expected = (len(exposures), k - 1, scene.intrinsics.height, scene.intrinsics.width)
    if cache.is_complete() and cached.is_file():
        maps = np.load(cached, mmap_mode="r")
        check_event_maps_shape(maps.shape, expected, cached, "the scene's images and k (cache)")
        return maps
    CONSOLE.log(f"Binning {scene.events_path} into event maps (once; cached in {cache.path})")
    with scene.open_events() as source:
        names = [str(e.file) for e in exposures]
        check_event_coverage(source, exposures, names, k, hint=f"check {EVENTS_FILE}, {TIMESTAMPS_FILE} and their units")
        maps = exposure_bins(source, exposures, k)
    cache.begin()
    np.save(cached, maps)
    cache.finish({"shape": list(maps.shape), "events_unit": scene.events_unit})
    return np.load(cached, mmap_mode="r")


def read_evdeblurnerf(
    root: Path,
    theta: Optional[float] = None,
    color_space: Optional[str] = None,
    clip_max: float = 1.0,
    k: Optional[int] = None,
    coordinates: str = DEFAULT_COORDINATES,
) -> SceneRecord:
    """Read an EvDeblurNeRF scene for training: bins its events and computes EDI latents once (cached).

    Args:
        root: the scene folder.
        theta: contrast threshold for EDI (default: the authors' for the scene kind, 0.25 for a
            CDAVIS scene with ev_map.npz, else 0.2).
        color_space: encoding of the pixels (default "linear").
        clip_max: EDI latents are clipped to [0, clip_max] in linear intensity.
        k: latents per blurry frame (default DEFAULT_K).
        coordinates: "bilinear" (default) or "round", for rectified event coordinates.

    Raises:
        FileNotFoundError / ValueError: see :func:`read_evdeblurnerf_folder`; also events that
            do not cover an exposure (naming the file and the frame).
    """
    scene = read_evdeblurnerf_folder(root, coordinates=coordinates)
    k = int(k if k is not None else DEFAULT_K)
    if k < 2:
        raise ValueError(f"k must be at least 2 (one event bin), got {k}")
    exposures = scene.exposures()
    event_maps = _cached_event_maps(scene, exposures, k)
    edi = layout_edi_config(k, theta, scene.default_theta, color_space, clip_max)
    blurry_paths = [e.file for e in exposures]
    latents = cached_edi_latents(scene.root, blurry_paths, event_maps, edi, sources=scene.source_files())
    times_us = np.stack([latent_times_us(e.start_us, e.end_us, k) for e in exposures])
    t0, t1 = int(times_us.min()), int(times_us.max())
    span = float(max(t1 - t0, 1))
    blurry_index, latent_index = latent_grid(len(exposures), k)
    novel = None
    if scene.sharp:
        sharp = scene.sharp
        novel = ViewSet(
            intrinsics=scene.intrinsics,
            camera_to_worlds=scene.image_c2w[sharp],
            times=np.clip((scene.mid_us[sharp] - t0) / span, 0.0, 1.0),
            image_paths=[scene.image_paths[i] for i in sharp],
        )
    record = SceneRecord(
        root=scene.root,
        layout=LAYOUT_NAME,
        intrinsics=scene.intrinsics,
        k=k,
        theta=edi.theta,
        color_space=edi.color_space,
        latent_c2w=scene.latent_poses(exposures, k).reshape(-1, 4, 4),
        latent_times=(times_us.reshape(-1) - t0) / span,
        blurry_index=blurry_index,
        latent_index=latent_index,
        latent_image_paths=[p for row in latents for p in row],
        blurry_image_paths=blurry_paths,
        event_maps=event_maps,
        pose_source="given",
        novel=novel,
        notes={"events_unit": scene.events_unit, "events_unit_detected": scene.events_unit_detected,
               "camera_path": scene.path_source, "rectified_events": scene.rectified_events,
               "event_coordinates": scene.coordinates if scene.rectified_events else "integer",
               "theta_source": "given" if theta is not None else scene.default_theta_origin},
    )
    record.check()
    return record

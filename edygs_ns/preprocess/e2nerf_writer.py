"""Write a raw capture (``edygs-synth`` output) in E2NeRF's real-data layout, for measuring that route.

The E2NeRF real layout (:mod:`.e2nerf`) stores blurry frames, one LLFF pose per latent and the
events pre-binned into 4 bins per frame, but no timestamps. Written here from a raw capture:

- ``images/{5 i:03d}.png``: the blurry frames (PNG, lossless);
- ``events.pt``: float32 [n, 4, H*W] signed counts between the 5 evenly spaced latent instants of
  each exposure (the layout's convention);
- ``poses_bounds.npy``: [n * 5, 17], the ground-truth camera at each latent instant (the raw
  capture's ``gt/transforms.json``, interpolated when its k is not 5), hwf of the calibration,
  near/far from the room of ``scene.json`` (else from the camera path);
- ``gt/``: the raw capture's ground truth with every ``time_us`` moved onto the nominal clock that
  ``edygs-process --e2nerf`` gives the frames (exposure i starts at i x 200 ms and lasts 4 x
  25.001 ms; linear inside an exposure and between exposures), so that ``edygs-process --e2nerf``
  can copy it into the processed scene for ``edygs-eval``. Its latent frames keep the instants that
  are layout latents, renumbered (a capture with k = 3 gives latents 0, 2, 4 only, so no per-latent
  ground truth: write the capture with k = 5). E2NeRF's own scenes have no gt/.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any, Dict, List, Sequence

import numpy as np

from edygs_ns.events.accumulate import exposure_bins
from edygs_ns.events.exposures import Exposure, read_exposures
from edygs_ns.events.readers import open_event_source
from edygs_ns.io.images import write_rgb_png
from edygs_ns.preprocess import e2nerf, llff
from edygs_ns.preprocess.frames import read_frames
from edygs_ns.preprocess.inputs import (
    E2NERF_FRAME_PERIOD_US, E2NERF_REAL_EXPOSURE_US, GT_DIR_NAME, GT_TRANSFORMS_NAME, SCENE_JSON_NAME,
    poses_from_transforms,
)

#: Latents per frame of the layout (E2NeRF's 4 bins).
K = e2nerf.BINS + 1
#: A ground-truth latent whose instant lies within this fraction of a bin of a layout latent is that latent.
SLOT_TOLERANCE = 1e-6
#: Near plane written when the room is known (world units).
NEAR = 0.1


def nominal_clock(exposures: Sequence[Exposure], times_us: np.ndarray) -> np.ndarray:
    """Raw-capture instants [T] (µs) on E2NeRF's nominal clock: piecewise linear through every
    exposure's start and end (frame i over [i * 200 ms, i * 200 ms + 100.004 ms]); int64."""
    raw = np.array([[e.start_us, e.end_us] for e in exposures], dtype=np.float64).reshape(-1)
    starts = np.arange(len(exposures), dtype=np.float64) * E2NERF_FRAME_PERIOD_US
    nominal = np.stack([starts, starts + E2NERF_REAL_EXPOSURE_US], axis=1).reshape(-1)
    return np.round(np.interp(np.asarray(times_us, dtype=np.float64), raw, nominal)).astype(np.int64)


def _depth_bounds(raw: Path, centres: np.ndarray) -> List[float]:
    """[near, far]: NEAR to the farthest room corner (scene.json), else 0.1 to 10 path diameters."""
    scene_json = raw / SCENE_JSON_NAME
    if scene_json.is_file():
        scene = json.loads(scene_json.read_text())
        if "room_min" in scene and "room_max" in scene:
            corners = np.array(np.meshgrid(*zip(scene["room_min"], scene["room_max"]))).reshape(3, -1).T
            return [NEAR, float(np.max(np.linalg.norm(corners[None] - centres[:, None], axis=-1)))]
    diameter = float(np.max(np.linalg.norm(centres[None] - centres[:, None], axis=-1))) or 1.0
    return [0.1 * diameter, 10.0 * diameter]


def _layout_latents(frames: List[Dict[str, Any]], exposures: Sequence[Exposure]) -> List[Dict[str, Any]]:
    """The raw capture's ground-truth latent frames that fall on one of the layout's 5 latent instants,
    with ``latent_index`` renumbered among those 5 (all of them when the capture's k is 5)."""
    kept = []
    for frame in frames:
        exposure = exposures[int(frame["blurry_index"])]
        slot = (int(frame["time_us"]) - exposure.start_us) * (K - 1) / float(exposure.end_us - exposure.start_us)
        if abs(slot - round(slot)) < SLOT_TOLERANCE:
            kept.append(dict(frame, latent_index=int(round(slot))))
    return kept


def write_e2nerf_real(raw: Path, output: Path) -> Path:
    """Write the raw capture in ``raw`` (exposures.csv, events.h5, gt/) as an E2NeRF real scene.

    Args:
        raw: the raw capture folder written by edygs-synth.
        output: the new scene folder (must not exist, or be empty).

    Returns:
        ``output``.

    Raises:
        FileExistsError: ``output`` holds files.
        FileNotFoundError / ValueError: the raw capture lacks a file or is inconsistent (named).
    """
    import torch

    raw, output = Path(raw), Path(output)
    if output.exists() and any(output.iterdir()):
        raise FileExistsError(f"{output}: folder exists and is not empty")
    exposures = read_exposures(raw / "exposures.csv")
    frames, _ = read_frames([e.file for e in exposures])
    height, width = frames[0].shape[:2]
    (output / e2nerf.IMAGES_FOLDER).mkdir(parents=True, exist_ok=True)
    for i, frame in enumerate(frames):
        write_rgb_png(output / e2nerf.IMAGES_FOLDER / f"{5 * i:03d}.png", frame)
    with open_event_source(raw / "events.h5") as source:
        bins = exposure_bins(source, exposures, K)
    torch.save(torch.from_numpy(bins.reshape(len(exposures), K - 1, height * width)), output / e2nerf.EVENT_FILES[0])
    gt = raw / GT_DIR_NAME
    poses = poses_from_transforms(gt / GT_TRANSFORMS_NAME, exposures, K, (height, width))
    c2w = poses.c2w.reshape(-1, 4, 4)
    rows = llff.c2w_to_rows(c2w, height, width, poses.intrinsics.fl_x, *_depth_bounds(raw, c2w[:, :3, 3]))
    np.save(output / e2nerf.POSES_BOUNDS_FILE, rows)
    shutil.copytree(gt, output / GT_DIR_NAME)
    meta = json.loads((output / GT_DIR_NAME / GT_TRANSFORMS_NAME).read_text())
    meta["frames"] = _layout_latents(meta.get("frames", []), exposures)
    span = float((len(exposures) - 1) * E2NERF_FRAME_PERIOD_US + E2NERF_REAL_EXPOSURE_US)
    for key in ("frames", "novel_frames"):
        entries = [f for f in meta.get(key, []) if "time_us" in f]
        if entries:
            moved = nominal_clock(exposures, np.array([f["time_us"] for f in entries]))
            for entry, t in zip(entries, moved):
                entry["time_us"], entry["time"] = int(t), float(t) / span
    (output / GT_DIR_NAME / GT_TRANSFORMS_NAME).write_text(json.dumps(meta, indent=1))
    return output

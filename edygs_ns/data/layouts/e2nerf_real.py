"""Reader for E2NeRF's real (LLFF-style) scenes, captured with a DAVIS346.

Folder::

    images/000.jpg, 005.jpg, ...   blurry frames, in name order (E2NeRF names them {5*i:03d}.jpg)
    poses_bounds.npy               [views * k, 17]: one row per LATENT, in time order
    events.pt (or event.pt)        float tensor [views, 4, H*W] (or [views, 4, H, W]): signed
                                   counts, 4 bins per view

A poses_bounds row is a 3x5 matrix [R | t | hwf] flattened row-major, then near and far.
LLFF orders the rotation columns (down, right, back); we reorder them to OpenGL's
(right, up, back): right = column 1, up = -column 0, back = column 2. hwf holds the image
height, width and focal length of the images the poses were computed on; the focal length is
rescaled to the stored images' width, and the principal point is the image centre.

E2NeRF's conventions for this data (its public loader and EDI.py): the bins are fixed 25.001 ms
windows from the exposure start (event at t goes to bin int((t - start) / 25001)), so latent j
sits at start + j * 25.001 ms; the bins are equally long, which is what our latents assume (k
evenly spaced latents over 4 x 25.001 ms). Its EDI uses Θ = 0.3 (DEFAULT_THETA here; its event
loss uses 0.3 for positive and 0.2 for negative events).

There is no ground truth. EDI latents are computed once and cached. The files carry no
timestamps: latents are evenly spaced over [0, 1] (exposures back to back).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from edygs_ns.data.event_maps import cached_edi_latents, cached_events_pt
from edygs_ns.data.layouts.common import (
    E2NERF_EVENT_FILES,
    find_e2nerf_events,
    SceneRecord,
    latent_grid,
    uniform_latent_times,
)
from edygs_ns.io.images import image_size
from edygs_ns.events.edi import EdiConfig
from edygs_ns.geometry import Intrinsics, llff_to_opengl

#: Pose file.
POSES_BOUNDS_FILE = "poses_bounds.npy"
#: Folder of blurry frames.
IMAGES_FOLDER = "images"
#: Event counts file (E2NeRF's README calls it event.pt; either is read, events.pt first).
EVENTS_FILE = E2NERF_EVENT_FILES[0]
#: Image file suffixes accepted in images/ (compared lower-case).
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
#: Columns of a poses_bounds row: 15 for the 3x5 pose matrix, 2 for near/far.
POSE_COLUMNS = 15
BOUNDS_COLUMNS = 2
#: A 3x5 LLFF pose: rows, columns.
LLFF_ROWS, LLFF_COLS = 3, 5
#: Default contrast threshold for E2NeRF real data: the Θ of E2NeRF's EDI.py.
DEFAULT_THETA = 0.3
#: E2NeRF's real-data event bins: fixed windows of this many µs from the exposure start.
E2NERF_BIN_US = 25_001
#: Default pixel encoding for E2NeRF data (DAVIS APS frames are linear).
DEFAULT_COLOR_SPACE = "linear"


def is_e2nerf_real(root: Path) -> bool:
    """An E2NeRF real scene has poses_bounds.npy, events.pt (or event.pt) and an images/ folder."""
    return (root / POSES_BOUNDS_FILE).is_file() and find_e2nerf_events(root) is not None and (root / IMAGES_FOLDER).is_dir()


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
        ValueError: poses_bounds.npy or events.pt disagree with the images (names the file and
            both shapes).
    """
    folder = root / IMAGES_FOLDER
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES) if folder.is_dir() else []
    if not images:
        raise FileNotFoundError(f"{folder}: no blurry frames ({', '.join(IMAGE_SUFFIXES)})")
    height, width = image_size(images[0])
    events = find_e2nerf_events(root) or root / EVENTS_FILE
    event_maps = cached_events_pt(events, len(images), height, width, root)
    k = int(event_maps.shape[1]) + 1

    poses_file = root / POSES_BOUNDS_FILE
    rows = np.load(poses_file, allow_pickle=False)
    expected = (len(images) * k, POSE_COLUMNS + BOUNDS_COLUMNS)
    if rows.shape != expected:
        raise ValueError(
            f"{poses_file}: has shape {rows.shape}, expected {expected}: one row per latent "
            f"({len(images)} images x k={k} latents, k from {events.name}'s {k - 1} bins)"
        )
    llff = rows[:, :POSE_COLUMNS].reshape(-1, LLFF_ROWS, LLFF_COLS).astype(np.float64)
    if not np.all(np.isfinite(llff)):
        raise ValueError(f"{poses_file}: holds non-finite values")
    hwf_width, focal = float(llff[0, 1, 4]), float(llff[0, 2, 4])
    focal = focal * width / hwf_width if hwf_width > 0 else focal

    edi = EdiConfig(
        k=k,
        theta=float(theta if theta is not None else DEFAULT_THETA),
        color_space=color_space or DEFAULT_COLOR_SPACE,  # type: ignore[arg-type]
        clip_max=clip_max,
    )
    latents = cached_edi_latents(root, images, event_maps, edi, sources=[events])
    blurry_index, latent_index = latent_grid(len(images), k)
    record = SceneRecord(
        root=root,
        layout="e2nerf-real",
        intrinsics=Intrinsics(width=width, height=height, fl_x=focal, fl_y=focal, cx=width / 2.0, cy=height / 2.0),
        k=k,
        theta=edi.theta,
        color_space=edi.color_space,
        latent_c2w=llff_to_opengl(llff),
        latent_times=uniform_latent_times(len(images), k),
        blurry_index=blurry_index,
        latent_index=latent_index,
        latent_image_paths=[p for row in latents for p in row],
        blurry_image_paths=images,
        event_maps=event_maps,
        pose_source="given",
        notes={"theta_source": "given" if theta is not None else "E2NeRF's EDI.py (real data)",
               "event_bins": f"E2NeRF's fixed {E2NERF_BIN_US} µs windows from each exposure start",
               "events_file": events.name},
    )
    record.check()
    return record

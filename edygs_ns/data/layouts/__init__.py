"""Scene folder layouts: detect which one a folder has and read it into a SceneRecord."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable, Dict, Optional, Tuple

from edygs_ns.data.layouts.common import LAYOUT_NAMES, SceneRecord
from edygs_ns.data.layouts.e2nerf_real import read_e2nerf_real
from edygs_ns.data.layouts.e2nerf_synthetic import read_e2nerf_synthetic
from edygs_ns.data.layouts.evdeblurnerf import read_evdeblurnerf
from edygs_ns.preprocess import e2nerf
from edygs_ns.preprocess.evdeblurnerf import is_evdeblurnerf
from edygs_ns.data.layouts.processed import DEFAULT_EVENT_MAPS_FILE, TRANSFORMS_FILE, is_processed, read_processed

#: What each layout needs, quoted when a folder matches none.
LAYOUT_REQUIREMENTS: Dict[str, str] = {
    "processed": "transforms.json + event_maps.npy (written by edygs-process)",
    "e2nerf-synthetic": "transform_train.json + events.pt (or event.pt) + train/r_<i>.png",
    "e2nerf-real": "poses_bounds.npy + events.pt (or event.pt) + images/",
    "evdeblurnerf": "poses_bounds.npy + events.h5 + images_1/ with timestamps.npz",
}
#: Files that mark a raw capture, which must go through edygs-process first.
RAW_CAPTURE_MARKER = "exposures.csv"
#: transforms.json keys that only edygs-process writes (a processed scene with a file missing).
PROCESSED_MARKER_KEYS = ("event_maps", "exposures", "k")

#: Layout name -> (detector, reader) in detection order.
_LAYOUTS: Dict[str, Tuple[Callable[[Path], bool], Callable[..., SceneRecord]]] = {
    "processed": (is_processed, read_processed),
    "e2nerf-synthetic": (e2nerf.is_synthetic, read_e2nerf_synthetic),
    "e2nerf-real": (e2nerf.is_real, read_e2nerf_real),
    "evdeblurnerf": (is_evdeblurnerf, read_evdeblurnerf),
}


def detect_layout(root: Path) -> str:
    """The layout of a scene folder, judged by the files present.

    Raises:
        FileNotFoundError: the folder does not exist.
        ValueError: the folder matches no layout; the message lists what each layout needs.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: scene folder not found")
    for name, (detect, _) in _LAYOUTS.items():
        if detect(root):
            return name
    missing = _missing_event_maps(root)
    if missing is not None:
        raise FileNotFoundError(
            f"{missing}: event maps of the processed scene {root} are missing (its transforms.json names them); "
            "run edygs-process again to rewrite the scene"
        )
    expected = "; ".join(f"{name}: {needs}" for name, needs in LAYOUT_REQUIREMENTS.items())
    hint = ""
    if (root / RAW_CAPTURE_MARKER).is_file():
        hint = " It looks like a raw capture: run `edygs-process` on it first."
    raise ValueError(f"{root}: not a recognised scene folder. Expected one of: {expected}.{hint}")


def _missing_event_maps(root: Path) -> Optional[Path]:
    """The event maps file a processed scene's transforms.json names, when that file is gone; else None."""
    transforms = root / TRANSFORMS_FILE
    if not transforms.is_file():
        return None
    try:
        meta = json.loads(transforms.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        return None
    if not isinstance(meta, dict) or not all(key in meta for key in PROCESSED_MARKER_KEYS):
        return None
    path = root / str(meta.get("event_maps") or DEFAULT_EVENT_MAPS_FILE)
    return None if path.is_file() else path


def read_scene(
    root: Path,
    layout: str = "auto",
    theta: Optional[float] = None,
    color_space: Optional[str] = None,
    clip_max: float = 1.0,
    k: Optional[int] = None,
) -> SceneRecord:
    """Read a scene folder of any supported layout.

    Args:
        root: the scene folder.
        layout: "auto" (detect) or one of LAYOUT_NAMES.
        theta: contrast threshold override (None: the processed scene's own, i.e. estimated or
            given at edygs-process; for a layout read directly, the authors' value for it:
            0.3 E2NeRF real, 0.2 E2NeRF synthetic, 0.2 / 0.25 EvDeblurNeRF Blender / CDAVIS).
        color_space: pixel encoding override (None: the scene's own, or "linear").
        clip_max: EDI clip for layouts whose latents are computed here.
        k: latents per blurry frame for layouts that leave it open (EvDeblurNeRF; None: its default).

    Raises:
        ValueError: unknown layout name, or a folder that does not match.
        FileNotFoundError: missing folder or files.
    """
    root = Path(root)
    name = detect_layout(root) if layout == "auto" else layout
    if name not in _LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; choose 'auto' or one of {LAYOUT_NAMES}")
    if layout != "auto" and not root.is_dir():
        raise FileNotFoundError(f"{root}: scene folder not found")
    _, reader = _LAYOUTS[name]
    if name == "processed":
        return reader(root, theta=theta, color_space=color_space)
    if name == "evdeblurnerf":
        return reader(root, theta=theta, color_space=color_space, clip_max=clip_max, k=k)
    return reader(root, theta=theta, color_space=color_space, clip_max=clip_max)

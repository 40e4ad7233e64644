"""Compute-once, on-disk cache of event maps and of what is derived from them (EDI latents).

Everything derived from a scene's source files is written under ``<scene>/edygs_cache/`` in a
folder named ``<kind>_<key>``. The key hashes the parameters (k, theta, colour space, ...) and
each source file's name, size and modification time, so editing a source or changing a
parameter gives a new folder; the stale folder of the same kind is removed. A folder counts
as complete only once its ``manifest.json`` is written (the last step), so an interrupted run
is recomputed rather than half-read. Nothing here runs per training iteration.

The dataparser's layouts read directly (E2NeRF, EvDeblurNeRF) cache here; :func:`write_edi_latents`
is the one EDI loop, shared with the ``edi`` step of ``edygs-process``. That command's resumable
steps (:mod:`.steps`) keep their own record: they build one output folder from inputs kept
elsewhere (so their fingerprints name absolute paths, and a changed finished step is an error, not
a silent recompute), while these caches sit beside their sources (keyed on file names, so a moved
scene keeps its cache) and are simply rebuilt when stale.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence

import numpy as np

from edygs_ns.events.edi import EdiConfig, edi_from_frame
from edygs_ns.io.images import UINT8_MAX, read_rgb_uint8, save_rgb_uint8, write_rgb_png
from edygs_ns.preprocess.e2nerf import read_event_bins
from edygs_ns.preprocess.steps import progress_bar

#: Folder inside the scene folder that holds every cache.
CACHE_DIR_NAME = "edygs_cache"
#: Written last into a cache folder; its presence (with the right key) marks the folder complete.
MANIFEST_NAME = "manifest.json"
#: Hex digits of the hash kept in a cache folder's name.
KEY_LENGTH = 12
#: File name of cached event maps inside their cache folder.
EVENT_MAPS_FILE = "event_maps.npy"


def _fingerprint(paths: Sequence[Path]) -> List[Dict[str, Any]]:
    """Name, size and mtime (ns) of each file: what decides whether a cache is still valid."""
    out = []
    for path in paths:
        stat = Path(path).stat()
        out.append({"name": Path(path).name, "size": int(stat.st_size), "mtime_ns": int(stat.st_mtime_ns)})
    return out


class CacheFolder:
    """A keyed cache folder ``<scene>/edygs_cache/<kind>_<key>``.

    Args:
        scene_root: the scene folder.
        kind: what the folder holds (e.g. "event_maps", "edi_latents").
        params: parameters the content depends on (JSON-serialisable).
        sources: files the content is computed from.
    """

    def __init__(self, scene_root: Path, kind: str, params: Dict[str, Any], sources: Sequence[Path]):
        self.kind = kind
        self.manifest = {"kind": kind, "params": params, "sources": _fingerprint(sources)}
        digest = hashlib.sha1(json.dumps(self.manifest, sort_keys=True).encode("utf-8")).hexdigest()
        self.key = digest[:KEY_LENGTH]
        self.parent = Path(scene_root) / CACHE_DIR_NAME
        self.path = self.parent / f"{kind}_{self.key}"

    def is_complete(self) -> bool:
        """True when the folder was fully written for exactly these parameters and sources."""
        manifest = self.path / MANIFEST_NAME
        if not manifest.is_file():
            return False
        try:
            with open(manifest, encoding="utf-8") as handle:
                return json.load(handle).get("key") == self.key
        except (OSError, json.JSONDecodeError):
            return False

    def begin(self) -> Path:
        """Remove stale folders of this kind and any partial copy of this one; return a fresh folder."""
        if self.parent.is_dir():
            for old in self.parent.glob(f"{self.kind}_*"):
                if old.is_dir():
                    shutil.rmtree(old)
        self.path.mkdir(parents=True, exist_ok=True)
        return self.path

    def finish(self, extra: Optional[Dict[str, Any]] = None) -> None:
        """Write the manifest, marking the folder complete."""
        content = dict(self.manifest, key=self.key, **(extra or {}))
        with open(self.path / MANIFEST_NAME, "w", encoding="utf-8") as handle:
            json.dump(content, handle, indent=2)


def check_event_maps_shape(shape: Sequence[int], expected: Sequence[Optional[int]], source: Path, what: str) -> None:
    """Raise ValueError naming ``source`` and both shapes unless ``shape`` matches ``expected``.

    Args:
        shape: the shape found.
        expected: the shape required; None entries match any size.
        source: the file the array came from.
        what: a phrase saying where the expected shape comes from.
    """
    shape = tuple(int(s) for s in shape)
    ok = len(shape) == len(expected) and all(e is None or s == e for s, e in zip(shape, expected))
    if not ok:
        wanted = "(" + ", ".join("any" if e is None else str(e) for e in expected) + ")"
        raise ValueError(f"{source}: event data has shape {shape}, expected {wanted} from {what}")


def load_event_maps_npy(path: Path, n_blurry: int, k: int, height: int, width: int) -> np.ndarray:
    """Open a processed scene's event_maps.npy (memory-mapped) and check its shape.

    Args:
        path: the .npy file, float32 [n_blurry, k-1, H, W].
        n_blurry, k, height, width: what the scene's transforms.json describes.

    Returns:
        The read-only memory map (float32 when stored so).

    Raises:
        FileNotFoundError: no such file.
        ValueError: wrong shape or dtype; the message names the file and both shapes.
    """
    if not path.is_file():
        raise FileNotFoundError(f"{path}: event maps file not found")
    try:
        maps = np.load(path, mmap_mode="r", allow_pickle=False)
    except ValueError as err:
        raise ValueError(f"{path}: not a readable .npy array ({err})") from err
    what = f"transforms.json ({n_blurry} blurry frames, k={k}, {height}x{width} pixels)"
    check_event_maps_shape(maps.shape, (n_blurry, k - 1, height, width), path, what)
    if maps.dtype.kind != "f":
        raise ValueError(f"{path}: event maps must be floating point, found dtype {maps.dtype}")
    return maps


def cached_events_pt(events_pt: Path, n_views: int, height: int, width: int, scene_root: Path) -> np.ndarray:
    """E2NeRF's events.pt as event maps, converted once and cached as .npy.

    Args:
        events_pt: the file (events.pt, or event.pt as E2NeRF's README names it), a float tensor
            [views, bins, H*W] or [views, bins, H, W] of signed event counts.
        n_views: number of blurry images the scene has.
        height, width: their size in pixels.
        scene_root: the scene folder (the cache goes under it).

    Returns:
        float32 [views, bins, H, W] (a read-only memory map of the cache); k = bins + 1.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the view count or pixel count disagrees with the images (message names the
            file and both shapes), or the file is not a tensor.
    """
    from nerfstudio.utils.rich_utils import CONSOLE

    if not events_pt.is_file():
        raise FileNotFoundError(f"{events_pt}: event file not found")
    cache = CacheFolder(scene_root, "event_maps", {"format": "e2nerf-events.pt"}, [events_pt])
    cached = cache.path / EVENT_MAPS_FILE
    if cache.is_complete() and cached.is_file():
        maps = np.load(cached, mmap_mode="r")
        what = f"{n_views} blurry images of {width}x{height} pixels (cached from this file)"
        check_event_maps_shape(maps.shape, (n_views, None, height, width), events_pt, what)
        return maps
    CONSOLE.log(f"Converting {events_pt} to event maps (once; cached in {cache.path})")
    maps = read_event_bins(events_pt, n_views, height, width)
    cache.begin()
    np.save(cached, maps)
    cache.finish({"shape": list(maps.shape)})
    return np.load(cached, mmap_mode="r")


def cached_rgb_images(
    scene_root: Path, kind: str, sources: Sequence[Path], names: Sequence[str], background: Optional[float]
) -> List[Path]:
    """RGB copies of (possibly RGBA) images, composited once on a grey ``background`` and cached.

    Args:
        scene_root: the scene folder.
        kind: cache folder kind (e.g. "train_rgb").
        sources: the original images.
        names: output file name for each source.
        background: grey level in [0, 1] that transparent pixels are composited on, or None to
            drop alpha and keep the stored RGB (what a loader without white_bkgd does).

    Returns:
        Paths of the cached 8-bit RGB PNGs, one per source.
    """
    cache = CacheFolder(scene_root, kind, {"background": background, "names": list(names)}, sources)
    outputs = [cache.path / name for name in names]
    if cache.is_complete() and all(p.is_file() for p in outputs):
        return outputs
    from nerfstudio.utils.rich_utils import get_progress

    cache.begin()
    with get_progress(f"Compositing {kind} images") as progress:
        for i in progress.track(range(len(sources)), total=len(sources)):
            save_rgb_uint8(read_rgb_uint8(sources[i], background=background), outputs[i])
    cache.finish()
    return outputs


def cached_edi_latents(
    scene_root: Path,
    blurry_paths: Sequence[Path],
    event_maps: np.ndarray,
    config: EdiConfig,
    sources: Sequence[Path],
) -> List[List[Path]]:
    """EDI latent images of every exposure, computed once and cached as 8-bit PNGs.

    Args:
        scene_root: the scene folder.
        blurry_paths: n RGB blurry images (same encoding as config.color_space).
        event_maps: [n, k-1, H, W] signed event counts between consecutive latents.
        config: EDI settings (k must equal event_maps.shape[1] + 1).
        sources: every file the latents depend on (event file, original blurry images): a
            change in any of them invalidates the cache.

    Returns:
        [n][k] paths; entry [b][j] is latent j of exposure b (``<b:04d>_<j>.png``), in the same
        colour encoding as the blurry images.
    """
    from nerfstudio.utils.rich_utils import CONSOLE

    if event_maps.shape[1] != config.k - 1:
        raise ValueError(f"cached_edi_latents: event maps have {event_maps.shape[1]} bins, k={config.k} needs {config.k - 1}")
    params = {"k": config.k, "theta": config.theta, "color_space": config.color_space, "clip_max": config.clip_max}
    cache = CacheFolder(scene_root, "edi_latents", params, list(sources) + list(blurry_paths))
    paths = [[cache.path / f"{b:04d}_{j}.png" for j in range(config.k)] for b in range(len(blurry_paths))]
    if cache.is_complete() and all(p.is_file() for row in paths for p in row):
        return paths
    CONSOLE.log(f"Computing EDI latents for {len(blurry_paths)} blurry frames (once; cached in {cache.path})")
    cache.begin()
    with progress_bar("EDI latents", len(blurry_paths)) as advance:
        write_edi_latents(blurry_paths, event_maps, config, paths, advance)
    cache.finish()
    return paths


def write_edi_latents(
    blurry_paths: Sequence[Path],
    event_maps: np.ndarray,
    config: EdiConfig,
    out_paths: Sequence[Sequence[Path]],
    advance: Optional[Callable[[], None]] = None,
) -> None:
    """The EDI step of every route: latents of each blurry frame from its event bins, as 8-bit PNGs.

    Args:
        blurry_paths: n RGB blurry images (encoded as config.color_space).
        event_maps: [n, k-1, H, W] signed counts (an array or a memory map).
        config: EDI settings (Θ, k, colour space, clip).
        out_paths: [n][k] output files; latent j of frame b goes to out_paths[b][j].
        advance: called once per frame done (a progress bar's), or None.
    """
    for b in range(len(blurry_paths)):
        latents = edi_from_frame(read_rgb_uint8(blurry_paths[b]), np.asarray(event_maps[b]), config)
        out_paths[b][0].parent.mkdir(parents=True, exist_ok=True)
        for j in range(config.k):
            write_rgb_png(out_paths[b][j], np.clip(np.round(latents[j] * UINT8_MAX), 0, UINT8_MAX).astype(np.uint8))
        if advance is not None:
            advance()

"""Does the camera move? A cheap look at the frames before COLMAP spends minutes on them.

Structure from motion needs parallax: a camera that stays put (a DAVIS on a tripod watching
traffic) registers no image, which COLMAP only says after a long run. Here corners found in the
first frame are tracked (pyramidal Lucas-Kanade, checked forwards and backwards) into a few
frames spread over the clip; a track counts only when the patches around both ends look alike
(normalised cross-correlation), so frames of unrelated noise never pass for a still picture. The
median displacement of the tracked corners ignores the moving objects as long as most of the
picture is background. When that median stays below ``min_motion_px`` in every sampled frame,
the camera is static.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional, Sequence

import cv2
import numpy as np

#: Frames (after the first) the first frame is compared with, spread evenly over the clip.
SAMPLED_FRAMES = 8
#: Corners looked for in the first frame, their quality (fraction of the best) and spacing (px).
MAX_CORNERS = 400
CORNER_QUALITY = 0.01
CORNER_SPACING_PX = 5
#: Fewest corners for a judgement; with fewer (a featureless scene) COLMAP is left to decide.
MIN_CORNERS = 8
#: Lucas-Kanade window (px) and pyramid levels.
LK_WINDOW_PX = 21
LK_LEVELS = 3
#: A corner counts as tracked when the backward track returns within this distance (px).
FORWARD_BACKWARD_PX = 1.0
#: Below this fraction of tracked corners a frame has moved too far to track: the camera moves.
MIN_TRACKED_FRACTION = 0.3
#: Half size (px) of the patches compared at both ends of a track, and their least correlation.
PATCH_RADIUS_PX = 5
MIN_PATCH_NCC = 0.7


class StaticCameraError(ValueError):
    """The frames show no camera motion; the message names the choices left."""


def _grey(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise ValueError(f"{path}: cannot decode the image (truncated or not an image file)")
    return image


def _patches_match(ref: np.ndarray, frame: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """[C] bool: the patches around start (in ref) and end (in frame) correlate (NCC >= MIN_PATCH_NCC)."""
    r = PATCH_RADIUS_PX
    h, w = ref.shape
    ok = np.zeros(len(start), dtype=bool)
    for i, ((x0, y0), (x1, y1)) in enumerate(np.round(np.stack([start, end], axis=1)).astype(int)):
        if min(x0, y0, x1, y1) < r or max(x0, x1) >= w - r or max(y0, y1) >= h - r:
            continue
        a = ref[y0 - r: y0 + r + 1, x0 - r: x0 + r + 1].astype(np.float64).ravel()
        b = frame[y1 - r: y1 + r + 1, x1 - r: x1 + r + 1].astype(np.float64).ravel()
        a, b = a - a.mean(), b - b.mean()
        norm = np.sqrt((a @ a) * (b @ b))
        ok[i] = norm > 0 and (a @ b) / norm >= MIN_PATCH_NCC
    return ok


def median_displacements(frames: Sequence[np.ndarray]) -> Optional[List[float]]:
    """Median corner displacement (px) from frames[0] to each of the others; inf when untrackable.

    Args:
        frames: uint8 grey [H, W] images of one camera, in time order.

    Returns:
        One value per frame after the first, or None when the first frame has too few corners.
    """
    ref = frames[0]
    corners = cv2.goodFeaturesToTrack(ref, MAX_CORNERS, CORNER_QUALITY, CORNER_SPACING_PX)
    if corners is None or len(corners) < MIN_CORNERS:
        return None
    params = dict(winSize=(LK_WINDOW_PX, LK_WINDOW_PX), maxLevel=LK_LEVELS)
    out = []
    for frame in frames[1:]:
        moved, status, _ = cv2.calcOpticalFlowPyrLK(ref, frame, corners, None, **params)
        back, status_back, _ = cv2.calcOpticalFlowPyrLK(frame, ref, moved, None, **params)
        good = (status.reshape(-1) == 1) & (status_back.reshape(-1) == 1)
        good &= np.linalg.norm((back - corners).reshape(-1, 2), axis=1) < FORWARD_BACKWARD_PX
        good &= _patches_match(ref, frame, corners.reshape(-1, 2), moved.reshape(-1, 2))
        if good.sum() < MIN_TRACKED_FRACTION * len(corners):
            out.append(float("inf"))
            continue
        shift = np.linalg.norm((moved - corners).reshape(-1, 2)[good], axis=1)
        out.append(float(np.median(shift)))
    return out


def check_camera_moves(paths: Sequence[Path], min_motion_px: float) -> Optional[float]:
    """Raise StaticCameraError when the frames show no camera motion.

    Args:
        paths: the frames (EDI latents or blurry frames), in time order.
        min_motion_px: the largest median displacement must reach this; 0 disables the check.

    Returns:
        The largest median displacement (px), or None when not judged (disabled, one frame,
        too few corners).

    Raises:
        StaticCameraError: the camera does not move (the message names the choices left).
    """
    if min_motion_px <= 0 or len(paths) < 2:
        return None
    picks = np.unique(np.linspace(0, len(paths) - 1, SAMPLED_FRAMES + 1).round().astype(int))
    shifts = median_displacements([_grey(Path(paths[i])) for i in picks])
    if shifts is None:
        return None
    largest = max(shifts)
    if largest < min_motion_px:
        raise StaticCameraError(
            f"{Path(paths[0]).parent}: the camera does not move: tracked corners shift by at most {largest:.2f} px "
            f"(median) across {len(paths)} frames, below --colmap.min-motion-px {min_motion_px:g}; COLMAP cannot pose "
            "a static camera (no parallax). Choices: --poses given --given-poses FILE (a transforms.json with the "
            "camera's pose per time_us), or --colmap.min-motion-px 0 to run COLMAP anyway"
        )
    return largest

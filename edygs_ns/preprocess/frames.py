"""Blurry frames as read from disk (8- or 16-bit, grey/RGB/RGBA) to uint8 RGB, one bit depth per capture.

16-bit containers often hold fewer significant bits: a DAVIS's APS frames are 10-bit ADC codes
(aedat >= 2.3 yields them as ``I;16``, values up to 1023), and many machine-vision cameras save
12-bit data in 16-bit PNGs. Dividing such codes by 257 darkens the frames 16 to 64 times. So the
bit depth is decided once for all the frames of a capture (a per-frame decision would brighten
dark frames more than bright ones): given, or the smallest of :data:`BIT_DEPTHS` that holds the
largest code of every frame, and the decision is said in one line.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import cv2
import numpy as np
from edygs_ns.io.images import UINT8_MAX

#: Colour channels of every frame in a capture (RGB).
RGB_CHANNELS = 3
#: Bit depths a 16-bit container may hold, smallest first.
BIT_DEPTHS = (10, 12, 14, 16)
#: Bit depth of a 16-bit container whose codes say nothing (all zero).
FULL_DEPTH = 16


def read_raw_image(path: Path) -> np.ndarray:
    """An image file's pixels as stored (uint8 or uint16), channels in RGB(A) order.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file cannot be decoded (truncated or not an image); names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: image file not found")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ValueError(f"{path}: cannot decode the image (truncated or not an image file)")
    if raw.ndim == 3 and raw.shape[2] == RGB_CHANNELS:
        raw = cv2.cvtColor(raw, cv2.COLOR_BGR2RGB)
    elif raw.ndim == 3 and raw.shape[2] == RGB_CHANNELS + 1:
        raw = cv2.cvtColor(raw, cv2.COLOR_BGRA2RGBA)
    return raw


def infer_bit_depth(images: Sequence[np.ndarray], bits: Optional[int] = None) -> Tuple[Optional[int], str]:
    """The bit depth of a capture's 16-bit codes, and a note saying what was assumed.

    Args:
        images: the capture's frames as stored (alpha channels are not looked at).
        bits: the depth the user gave (one of BIT_DEPTHS), or None to infer it.

    Returns:
        (bits, note): None and "" when no frame is 16-bit; else the depth and a one-line note.

    Raises:
        ValueError: ``bits`` is not one of BIT_DEPTHS, or a code exceeds it.
    """
    wide = [im for im in images if im.dtype == np.uint16]
    if not wide:
        return None, ""
    colour = [im[..., :RGB_CHANNELS] if im.ndim == 3 and im.shape[2] == RGB_CHANNELS + 1 else im for im in wide]
    top = max(int(im.max()) if im.size else 0 for im in colour)
    if bits is not None:
        if bits not in BIT_DEPTHS:
            raise ValueError(f"frame bit depth must be one of {BIT_DEPTHS}, got {bits}")
        if top >= 1 << bits:
            raise ValueError(f"16-bit frames hold codes up to {top}, more than {bits}-bit data allows (--frame-bits)")
        return bits, f"16-bit frames read as {bits}-bit data (given; largest code {top})"
    depth = next((d for d in BIT_DEPTHS if top < 1 << d), FULL_DEPTH) if top > 0 else FULL_DEPTH
    return depth, (f"16-bit frames hold codes up to {top}: read as {depth}-bit data (scaled by 255/{(1 << depth) - 1}); "
                   "pass --frame-bits to override")


def to_rgb8(image: np.ndarray, name: str, alpha_background: Optional[str] = "white", bits: int = FULL_DEPTH) -> np.ndarray:
    """An image as stored (grey, RGB or RGBA; 8 or 16 bit) as uint8 [H, W, 3] RGB.

    Args:
        image: [H, W], [H, W, 1], [H, W, 3] or [H, W, 4] uint8/uint16, channels in RGB(A) order.
        name: the image's origin, for the error message.
        alpha_background: "white" or "black", what transparent pixels show, or "none": alpha is
            dropped and the stored RGB kept (a loader without white_bkgd); None or "auto" mean
            "white".
        bits: significant bits of uint16 codes (see :func:`infer_bit_depth`); 16-bit alpha is
            always full range.

    Raises:
        ValueError: unsupported dtype or channel count.
    """
    if image.dtype == np.uint16:
        codes = image.astype(np.float64)
        top = np.full(codes.shape[-1] if codes.ndim == 3 else 1, float((1 << bits) - 1))
        if codes.ndim == 3 and codes.shape[2] == RGB_CHANNELS + 1:
            top[-1] = float((1 << FULL_DEPTH) - 1)
        image = np.clip(np.round(codes / top * UINT8_MAX), 0, UINT8_MAX).astype(np.uint8)
    if image.dtype != np.uint8:
        raise ValueError(f"{name}: unsupported pixel type {image.dtype} (expected 8- or 16-bit)")
    if image.ndim == 2:
        image = image[..., None]
    channels = image.shape[2]
    if channels == 1:
        return np.repeat(image, RGB_CHANNELS, axis=2)
    if channels == RGB_CHANNELS:
        return np.ascontiguousarray(image)
    if channels == RGB_CHANNELS + 1 and alpha_background == "none":
        return np.ascontiguousarray(image[..., :RGB_CHANNELS])
    if channels == RGB_CHANNELS + 1:
        alpha = image[..., 3:].astype(np.float32) / UINT8_MAX
        background = 0.0 if alpha_background == "black" else float(UINT8_MAX)
        rgb = image[..., :3].astype(np.float32) * alpha + background * (1.0 - alpha)
        return np.clip(np.round(rgb), 0, UINT8_MAX).astype(np.uint8)
    raise ValueError(f"{name}: unsupported channel count {channels} (expected 1, 3 or 4)")


def frames_to_rgb8(
    images: Sequence[np.ndarray], names: Sequence[str], alpha_background: Optional[str] = "white", bits: Optional[int] = None
) -> Tuple[List[np.ndarray], str]:
    """Every frame of a capture as uint8 RGB with one bit depth; returns (frames, note)."""
    depth, note = infer_bit_depth(images, bits)
    frames = [to_rgb8(im, name, alpha_background, depth or FULL_DEPTH) for im, name in zip(images, names)]
    return frames, note


def read_frames(
    paths: Sequence[Path], alpha_background: Optional[str] = "white", bits: Optional[int] = None
) -> Tuple[List[np.ndarray], str]:
    """Read image files as uint8 RGB frames with one bit depth (see :func:`frames_to_rgb8`)."""
    raws = [read_raw_image(Path(p)) for p in paths]
    return frames_to_rgb8(raws, [str(p) for p in paths], alpha_background, bits)

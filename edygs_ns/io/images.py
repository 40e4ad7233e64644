"""Image files as uint8 RGB arrays: read (grey, RGB or RGBA, alpha composited or dropped) and write.

``UINT8_MAX`` is the one definition of the 8-bit peak every package divides by.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Tuple

import cv2
import numpy as np
from PIL import Image

#: Largest 8-bit value.
UINT8_MAX = 255


def image_size(path: Path) -> Tuple[int, int]:
    """(height, width) of an image file without decoding its pixels."""
    with Image.open(path) as img:
        return int(img.height), int(img.width)


def read_rgb_uint8(path: Path, background: Optional[float] = None) -> np.ndarray:
    """Read an image as [H, W, 3] uint8.

    Args:
        path: image file (grey, RGB or RGBA).
        background: for images with alpha, the grey level in [0, 1] they are composited on
            (color = rgb * a + background * (1 - a)); None drops alpha without compositing.
    """
    with Image.open(path) as img:
        has_alpha = img.mode in ("RGBA", "LA") or (img.mode == "P" and "transparency" in img.info)
        if has_alpha and background is not None:
            rgba = np.asarray(img.convert("RGBA"), dtype=np.float32) / UINT8_MAX
            rgb = rgba[..., :3] * rgba[..., 3:] + background * (1.0 - rgba[..., 3:])
            return np.clip(np.round(rgb * UINT8_MAX), 0, UINT8_MAX).astype(np.uint8)
        return np.asarray(img.convert("RGB"), dtype=np.uint8)


def save_rgb_uint8(image: np.ndarray, path: Path) -> None:
    """Write an [H, W, 3] image (uint8, or float in [0, 1]) as 8 bits per channel (PIL; the format
    follows the suffix), creating the folder."""
    if image.dtype != np.uint8:
        image = np.clip(np.round(np.asarray(image, dtype=np.float64) * UINT8_MAX), 0, UINT8_MAX).astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path)


def write_rgb_png(path: Path, rgb: np.ndarray) -> None:
    """Write uint8 [H, W, 3] RGB as PNG (OpenCV: fast, for the many work products of edygs-process)."""
    if not cv2.imwrite(str(path), cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR)):
        raise OSError(f"{path}: could not write the image")

"""Colour encodings: the sRGB transfer function and the choice between linear and sRGB pixels.

EDI and the event model work on *linear* intensity. Pixel values read from disk are either
already linear (DAVIS APS frames, the E2NeRF data: ``color_space="linear"``) or sRGB-encoded
(``color_space="srgb"``). Every function here accepts numpy arrays or torch tensors with values
in [0, 1] and returns the same kind of array; torch is imported only when a tensor is passed.
"""

from __future__ import annotations

from typing import Any, Literal, Tuple

import numpy as np

#: sRGB-encoded values at or below this are on the linear segment of the sRGB curve.
SRGB_ENCODED_KNEE = 0.04045
#: Linear values at or below this are on the linear segment of the sRGB curve.
SRGB_LINEAR_KNEE = 0.0031308
#: Slope of the linear segment of the sRGB curve.
SRGB_LINEAR_SLOPE = 12.92
#: Offset a of the power segment: encoded = (1 + a) * linear ** (1 / gamma) - a.
SRGB_OFFSET = 0.055
#: Exponent of the power segment of the sRGB curve.
SRGB_GAMMA = 2.4

ColorSpace = Literal["linear", "srgb"]
#: The colour encodings understood by decode_to_linear / encode_from_linear.
COLOR_SPACES: Tuple[str, ...] = ("linear", "srgb")


def _is_numpy(x: Any) -> bool:
    return isinstance(x, (np.ndarray, np.generic, float, int))


def srgb_to_linear(x: Any) -> Any:
    """Decode sRGB-encoded values to linear intensity.

    Args:
        x: numpy array or torch tensor (any shape) of sRGB-encoded values in [0, 1].

    Returns:
        Linear intensity, same shape and array kind as ``x`` (floating point).
    """
    if _is_numpy(x):
        xf = np.asarray(x, dtype=np.result_type(np.asarray(x).dtype, np.float32))
        power = ((np.maximum(xf, SRGB_ENCODED_KNEE) + SRGB_OFFSET) / (1.0 + SRGB_OFFSET)) ** SRGB_GAMMA
        return np.where(xf <= SRGB_ENCODED_KNEE, xf / SRGB_LINEAR_SLOPE, power)
    import torch

    xf = x if torch.is_floating_point(x) else x.float()
    power = ((xf.clamp(min=SRGB_ENCODED_KNEE) + SRGB_OFFSET) / (1.0 + SRGB_OFFSET)) ** SRGB_GAMMA
    return torch.where(xf <= SRGB_ENCODED_KNEE, xf / SRGB_LINEAR_SLOPE, power)


def linear_to_srgb(x: Any) -> Any:
    """Encode linear intensity with the sRGB transfer function.

    Args:
        x: numpy array or torch tensor (any shape) of linear intensity in [0, 1].

    Returns:
        sRGB-encoded values, same shape and array kind as ``x`` (floating point).
    """
    if _is_numpy(x):
        xf = np.asarray(x, dtype=np.result_type(np.asarray(x).dtype, np.float32))
        power = (1.0 + SRGB_OFFSET) * np.maximum(xf, SRGB_LINEAR_KNEE) ** (1.0 / SRGB_GAMMA) - SRGB_OFFSET
        return np.where(xf <= SRGB_LINEAR_KNEE, xf * SRGB_LINEAR_SLOPE, power)
    import torch

    xf = x if torch.is_floating_point(x) else x.float()
    power = (1.0 + SRGB_OFFSET) * xf.clamp(min=SRGB_LINEAR_KNEE) ** (1.0 / SRGB_GAMMA) - SRGB_OFFSET
    return torch.where(xf <= SRGB_LINEAR_KNEE, xf * SRGB_LINEAR_SLOPE, power)


def _check_color_space(color_space: str) -> None:
    if color_space not in COLOR_SPACES:
        raise ValueError(f"unknown color_space {color_space!r}; expected one of {COLOR_SPACES}")


def decode_to_linear(img: Any, color_space: ColorSpace) -> Any:
    """Turn pixel values stored in ``color_space`` into linear intensity.

    Args:
        img: numpy array or torch tensor of pixel values in [0, 1] (any shape).
        color_space: "linear" (returned unchanged) or "srgb" (decoded).

    Returns:
        Linear intensity, same shape and array kind as ``img``.

    Raises:
        ValueError: unknown colour space.
    """
    _check_color_space(color_space)
    return img if color_space == "linear" else srgb_to_linear(img)


def encode_from_linear(img: Any, color_space: ColorSpace) -> Any:
    """Turn linear intensity into pixel values stored in ``color_space``.

    Args:
        img: numpy array or torch tensor of linear intensity in [0, 1] (any shape).
        color_space: "linear" (returned unchanged) or "srgb" (encoded).

    Returns:
        Pixel values in ``color_space``, same shape and array kind as ``img``.

    Raises:
        ValueError: unknown colour space.
    """
    _check_color_space(color_space)
    return img if color_space == "linear" else linear_to_srgb(img)

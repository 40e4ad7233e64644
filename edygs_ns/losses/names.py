"""The names of the loss terms: one enum, so that a misspelt name raises instead of never firing.

The model config weighs each term (``lambda_*``), :mod:`edygs_ns.model.phases` says which
terms count in which phase, and the model's loss dict is keyed by these values.
"""

from __future__ import annotations

from enum import Enum
from typing import Union


class LossName(str, Enum):
    """A loss term of EDyGS (the value is its key in the model's loss dict)."""

    EDI = "edi"
    """L1 + D-SSIM to the EDI latent"""
    EDI_STATIC = "edi_static"
    """the same on the static region only ((1 - M) weighted)"""
    EVENT = "event"
    """predicted vs measured event counts between two latents"""
    BLUR = "blur"
    """the blurry frame as the mean of the rendered latents"""
    MASK_L1 = "mask_l1"
    """sparsity of the motion mask"""
    MASK_CONSISTENCY = "mask_consistency"
    """the mask against the motion masks rendered at the switch"""
    MOTION = "motion"
    """size of the deformation"""


def loss_name(name: Union[str, LossName]) -> LossName:
    """``name`` as a LossName.

    Raises:
        ValueError: no loss term has that name (the message lists those that do).
    """
    try:
        return LossName(name)
    except ValueError:
        raise ValueError(f"unknown loss term {name!r}; the loss terms are {[n.value for n in LossName]}") from None

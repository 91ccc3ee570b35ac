"""What an object mask must be: one rule for a mask the app pushes with a frame
(``frame_input.check_frame``) and for a mask the app's ``Segmenter`` answers with
(``object/segmenter.py``), kept apart from the frame checks so that asking the segmenter does not
lead back into them."""

from __future__ import annotations

from typing import Any

import numpy as np

from kvtracker_sdk.errors import MaskError

__all__ = ["check_mask"]


def check_mask(mask: Any, size: tuple[int, int]) -> np.ndarray:
    """A bool [H, W] mask for an image of ``size`` (H, W), or MaskError."""
    if not isinstance(mask, np.ndarray):
        raise MaskError(f"mask must be a numpy array, got {type(mask).__name__}")
    if mask.ndim == 3 and mask.shape[2] == 1:
        mask = mask[..., 0]
    if mask.shape != size:
        raise MaskError(f"mask shape {mask.shape} does not match the image's {size}")
    if mask.dtype != np.bool_ and not np.issubdtype(mask.dtype, np.integer):
        raise MaskError(f"mask dtype must be bool or integer (non-zero = object), got {mask.dtype}")
    selected = mask.astype(bool, copy=False)
    if not selected.any():
        raise MaskError("mask selects no pixel")
    return selected

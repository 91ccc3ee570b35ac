"""Image preprocessing to a model's input resolution.

KV-Tracker resizes (no crop) so that both sides are multiples of the patch size and the pixel
count stays under ``d²`` with ``d`` in {224, 308, 518} (308 is its real-time setting). The
official Pi3 loader uses the same idea with a 255,000-pixel cap.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

__all__ = ["model_resolution", "resize_image", "resize_mask"]


def model_resolution(height: int, width: int, *, side: int = 308, patch_size: int = 14) -> tuple[int, int]:
    """(H, W) of the model input: aspect kept, multiples of ``patch_size``, H*W <= side²."""
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive, got {height}x{width}")
    scale = math.sqrt(side * side / (height * width))
    out_h = max(patch_size, int(height * scale) // patch_size * patch_size)
    out_w = max(patch_size, int(width * scale) // patch_size * patch_size)
    return out_h, out_w


def resize_image(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize uint8 RGB [H, W, 3] to ``size`` = (H, W): area filter down, cubic up."""
    out_h, out_w = size
    if image.shape[:2] == (out_h, out_w):
        return image
    shrinking = out_h * out_w < image.shape[0] * image.shape[1]
    interpolation = cv2.INTER_AREA if shrinking else cv2.INTER_CUBIC
    return cv2.resize(image, (out_w, out_h), interpolation=interpolation)


def resize_mask(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize a boolean mask [H, W] to ``size`` = (H, W) with nearest-neighbour sampling."""
    out_h, out_w = size
    if mask.shape[:2] == (out_h, out_w):
        return mask.astype(bool, copy=False)
    resized = cv2.resize(mask.astype(np.uint8), (out_w, out_h), interpolation=cv2.INTER_NEAREST)
    return resized.astype(bool)

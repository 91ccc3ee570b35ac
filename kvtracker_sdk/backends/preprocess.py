"""Image preprocessing to a model's input resolution.

KV-Tracker resizes (no crop) so that both sides are multiples of the patch size and the pixel
count stays under ``d²`` with ``d`` in {224, 308, 518} (308 is its real-time setting). The
official Pi3 loader uses the same idea with a 255,000-pixel cap.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

__all__ = ["fit_box", "model_resolution", "resize_image", "resize_mask", "to_uint8"]


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


def to_uint8(image: np.ndarray) -> np.ndarray:
    """uint8 RGB from uint8 (returned as is) or float in [0, 1] (rounded: k/255 maps back to k)."""
    if image.dtype == np.uint8:
        return image
    return np.round(np.clip(image.astype(np.float32), 0.0, 1.0) * 255.0).astype(np.uint8)


def fit_box(
    box: tuple[float, float, float, float],
    image_size: tuple[int, int],
    *,
    margin: float,
    aspect: float,
) -> tuple[int, int, int, int]:
    """Integer crop window (x0, y0, x1, y1) around ``box`` for object crops.

    The box is dilated by ``margin`` pixels on every side, grown (about its centre) to the
    height/width ratio ``aspect`` so that resizing the crop to the model input does not distort
    it, then shifted inside the image of size (H, W); it is clipped only if larger than the image.
    """
    height, width = image_size
    x0, y0, x1, y1 = box
    cx, cy = (x0 + x1) / 2.0, (y0 + y1) / 2.0
    w = x1 - x0 + 2.0 * margin
    h = y1 - y0 + 2.0 * margin
    if h / max(w, 1e-9) < aspect:
        h = w * aspect
    else:
        w = h / aspect
    w, h = min(w, float(width)), min(h, float(height))
    left = min(max(cx - w / 2.0, 0.0), width - w)
    top = min(max(cy - h / 2.0, 0.0), height - h)
    x_start, y_start = int(np.floor(left)), int(np.floor(top))
    x_stop = min(width, max(x_start + 1, int(np.ceil(left + w))))
    y_stop = min(height, max(y_start + 1, int(np.ceil(top + h))))
    return x_start, y_start, x_stop, y_stop

"""Object masks and boxes at model resolution: the same geometric resize as the image.

Masks follow KV-Tracker: resized as float32 with OpenCV bilinear, then ``> 0`` (a pixel touched
by the object stays in it). The legacy preprocessing used nearest-neighbour sampling and keeps
it, so that maps saved with it track as before. Resizes compose exactly (``PixelTransform``), so a
multi-step image plan and a single mask resize to the same final size map pixels identically.

Boxes are in pixels of the pushed frame: the object crop is dilated by its margin there (the
paper's 50 px are original-image pixels), then cropped and resized like the image.
"""

from __future__ import annotations

import enum
import math

import cv2
import numpy as np

from kvtracker_sdk.preprocess.sizing import Size

__all__ = ["BBox", "MaskResampling", "box_mask", "fit_box", "mask_bounds", "resize_mask"]

BBox = tuple[float, float, float, float]  # (x0, y0, x1, y1), pixels, x1/y1 exclusive


class MaskResampling(str, enum.Enum):
    """How a mask is resampled to model size."""

    BILINEAR_ANY = "bilinear-any"  # float32 bilinear, then > 0 (KV-Tracker)
    NEAREST = "nearest"  # nearest neighbour (the SDK's earlier, legacy-area-floor preprocessing)


def resize_mask(mask: np.ndarray, size: Size, resampling: MaskResampling) -> np.ndarray:
    """A bool [H, W] mask resized to ``size`` = (h, w) (bool out; a copy)."""
    out_h, out_w = size
    if mask.shape[:2] == (out_h, out_w):
        return np.array(mask, dtype=bool)
    if resampling is MaskResampling.BILINEAR_ANY:
        resized = cv2.resize(mask.astype(np.float32), (out_w, out_h), interpolation=cv2.INTER_LINEAR)
        return resized > 0
    nearest = cv2.resize(mask.astype(np.uint8), (out_w, out_h), interpolation=cv2.INTER_NEAREST)
    return nearest.astype(bool)


def box_mask(box: BBox, size: Size) -> np.ndarray:
    """bool [H, W] mask of the pixels a box covers (partly covered pixels included)."""
    x0, y0, x1, y1 = box
    mask = np.zeros(size, dtype=bool)
    mask[int(math.floor(y0)) : int(math.ceil(y1)), int(math.floor(x0)) : int(math.ceil(x1))] = True
    return mask


def mask_bounds(mask: np.ndarray) -> BBox:
    """The tight box (x0, y0, x1, y1) of a non-empty bool mask."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    return float(cols[0]), float(rows[0]), float(cols[-1] + 1), float(rows[-1] + 1)


def fit_box(box: BBox, image_size: Size, *, margin: float, aspect: float) -> tuple[int, int, int, int]:
    """Integer crop window (x0, y0, x1, y1) around ``box`` for object crops.

    The box is dilated by ``margin`` pixels of the image on every side, grown (about its centre)
    to the height/width ratio ``aspect`` so that resizing the crop to the model input does not
    distort it, then shifted inside the image of size (H, W); it is clipped only if larger than
    the image.
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

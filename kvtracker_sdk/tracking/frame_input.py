"""Validation and preprocessing of the frames, masks and boxes a user pushes.

Everything here is checked before the tracker changes anything, so a bad frame raises a typed
:class:`~kvtracker_sdk.errors.InputError` and leaves the tracker, its map and its cache untouched.

Accepted input (design doc, "Per-frame result"):

* ``image``: numpy [H, W, 3] RGB, uint8 or a float dtype with values in [0, 1]; H, W >= the
  model's patch size; the same H, W for the whole session.
* ``mask``: numpy [H, W] (or [H, W, 1]) bool or integer (non-zero = object), selecting at least
  one pixel, also after resizing to the model resolution.
* ``bbox``: (x0, y0, x1, y1) in pixels of the image, x0 < x1, y0 < y1, inside [0, W] x [0, H].
  Alone it acts as a rectangular mask; with a mask, the mask selects the object and the box only
  sets the crop region.

Output: a uint8 image at model resolution (multiples of the patch size, at most d² pixels), and in
object mode either the background blacked out (``ObjectPreprocessing.MASK``) or a crop around the
object dilated by ``crop_margin_px`` and grown to the model's aspect ratio (``CROP``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from kvtracker_sdk.backends.preprocess import (
    fit_box,
    model_resolution,
    resize_image,
    resize_mask,
    to_uint8,
)
from kvtracker_sdk.config import ObjectPreprocessing, TrackerConfig, TrackingMode
from kvtracker_sdk.errors import (
    BBoxError,
    ImageDtypeError,
    ImageShapeError,
    InputError,
    MaskError,
    NonFiniteImageError,
    ResolutionChangedError,
)

__all__ = ["FramePreparer", "PreparedFrame", "check_bbox", "check_image", "check_mask"]

BBox = tuple[float, float, float, float]


@dataclass(frozen=True)
class PreparedFrame:
    """A validated frame at model resolution, ready for a backend."""

    image: np.ndarray  # uint8 [h, w, 3] RGB at model resolution (object mode: masked or cropped)
    mask: np.ndarray | None  # bool [h, w] at model resolution, None when none was given
    input_size: tuple[int, int]  # (H, W) of the pushed image
    timestamp: float | None


def check_image(image: Any, *, min_side: int) -> np.ndarray:
    """The image as given (uint8 or float [0, 1]) after every check, or a typed InputError."""
    if not isinstance(image, np.ndarray):
        raise ImageDtypeError(f"image must be a numpy array, got {type(image).__name__}")
    if image.ndim != 3 or image.shape[2] != 3:
        raise ImageShapeError(f"image must be HxWx3 RGB, got shape {image.shape}")
    if image.shape[0] < min_side or image.shape[1] < min_side:
        raise ImageShapeError(
            f"image {image.shape[0]}x{image.shape[1]} is smaller than the model patch {min_side}"
        )
    if image.dtype == np.uint8:
        return image
    if not np.issubdtype(image.dtype, np.floating):
        raise ImageDtypeError(f"image dtype must be uint8 or float in [0, 1], got {image.dtype}")
    if not np.all(np.isfinite(image)):
        raise NonFiniteImageError("image contains NaN or infinite values")
    low, high = float(image.min()), float(image.max())
    if low < 0.0 or high > 1.0:
        raise ImageDtypeError(f"float image values must lie in [0, 1], got [{low:g}, {high:g}]")
    return image


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


def check_bbox(bbox: Any, size: tuple[int, int]) -> BBox:
    """(x0, y0, x1, y1) as floats inside an image of ``size`` (H, W), or BBoxError."""
    try:
        values = np.asarray(bbox, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise BBoxError(f"bbox must be 4 numbers (x0, y0, x1, y1), got {bbox!r}") from exc
    if values.shape != (4,) or not np.all(np.isfinite(values)):
        raise BBoxError(f"bbox must be 4 finite numbers (x0, y0, x1, y1), got {bbox!r}")
    x0, y0, x1, y1 = (float(v) for v in values)
    height, width = size
    if not (x0 < x1 and y0 < y1):
        raise BBoxError(f"bbox needs x0 < x1 and y0 < y1, got {values.tolist()}")
    if x0 < 0 or y0 < 0 or x1 > width or y1 > height:
        raise BBoxError(
            f"bbox {values.tolist()} lies outside the {width}x{height} image (clip it first)"
        )
    return x0, y0, x1, y1


def _check_timestamp(timestamp: Any) -> float | None:
    if timestamp is None:
        return None
    try:
        value = float(timestamp)
    except (TypeError, ValueError) as exc:
        raise InputError(f"timestamp must be a number or None, got {timestamp!r}") from exc
    if not math.isfinite(value):
        raise InputError(f"timestamp must be finite, got {value}")
    return value


def _box_mask(box: BBox, size: tuple[int, int]) -> np.ndarray:
    x0, y0, x1, y1 = box
    mask = np.zeros(size, dtype=bool)
    mask[int(math.floor(y0)) : int(math.ceil(y1)), int(math.floor(x0)) : int(math.ceil(x1))] = True
    return mask


def _bounds(mask: np.ndarray) -> BBox:
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    return float(cols[0]), float(rows[0]), float(cols[-1] + 1), float(rows[-1] + 1)


class FramePreparer:
    """Turns user frames into ``PreparedFrame``s for one tracker configuration."""

    def __init__(self, config: TrackerConfig, *, patch_size: int) -> None:
        self.config = config
        self.patch_size = int(patch_size)

    def model_size(self, input_size: tuple[int, int]) -> tuple[int, int]:
        """(h, w) at model resolution for an input of (H, W)."""
        return model_resolution(
            *input_size, side=self.config.resolution, patch_size=self.patch_size
        )

    def prepare(
        self,
        image: Any,
        *,
        timestamp: Any = None,
        mask: Any = None,
        bbox: Any = None,
        session_input_size: tuple[int, int] | None = None,
        map_resolution: tuple[int, int] | None = None,
    ) -> PreparedFrame:
        """Validate and convert one frame; raises an InputError subclass and changes nothing.

        ``session_input_size``: the (H, W) of the session's first frame (None: first frame).
        ``map_resolution``: the current map's model (h, w), which the frame must produce.
        """
        checked = check_image(image, min_side=self.patch_size)
        size = (int(checked.shape[0]), int(checked.shape[1]))
        if session_input_size is not None and size != tuple(session_input_size):
            raise ResolutionChangedError(
                f"image size changed from {tuple(session_input_size)} to {size} in mid-session; "
                "call reset() to start a session at the new size"
            )
        stamp = _check_timestamp(timestamp)
        object_mask = check_mask(mask, size) if mask is not None else None
        box = check_bbox(bbox, size) if bbox is not None else None
        if object_mask is None and box is not None:
            object_mask = _box_mask(box, size)
        object_mode = self.config.mode is TrackingMode.OBJECT
        if object_mode and object_mask is None:
            raise MaskError("object mode needs a mask or a bbox with every frame")

        out_size = self.model_size(size)
        if map_resolution is not None and out_size != tuple(map_resolution):
            raise ResolutionChangedError(
                f"frames of {size} give model input {out_size}, the map was built at "
                f"{tuple(map_resolution)}"
            )
        crop = self.config.object.preprocessing is ObjectPreprocessing.CROP
        if object_mode and crop and object_mask is not None:
            x0, y0, x1, y1 = fit_box(
                box if box is not None else _bounds(object_mask),
                size,
                margin=self.config.object.crop_margin_px,
                aspect=out_size[0] / out_size[1],
            )
            checked = checked[y0:y1, x0:x1]
            object_mask = object_mask[y0:y1, x0:x1]

        resized = resize_image(to_uint8(checked), out_size)
        small_mask = resize_mask(object_mask, out_size) if object_mask is not None else None
        if small_mask is not None and not small_mask.any():
            raise MaskError(f"the mask is too small: it selects no pixel at model size {out_size}")
        if np.may_share_memory(resized, image):
            resized = resized.copy()  # keyframes freeze their image: never freeze the user's array
        if object_mode and not crop and small_mask is not None:
            resized[~small_mask] = 0  # black background (KV-Tracker object mode)
        return PreparedFrame(np.ascontiguousarray(resized), small_mask, size, stamp)

"""Resampling a frame through a resize plan, with the exact pixel transform of what was done.

Frames are resized in their own dtype and converted to uint8 only at model size: a float frame
of 20000x20000 is never copied at full size (the conversion used to allocate four full-size
float32 temporaries, +9 GB for such a frame). uint8 frames — what both official pipelines take —
go through OpenCV exactly as there. A float frame resized before rounding can differ from
"round to uint8, then resize" by one level at some pixels (the order of two roundings).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from kvtracker_sdk.geometry.pixel_transform import PixelTransform
from kvtracker_sdk.preprocess.sizing import ResizeStep, Size, plan_output_size

__all__ = ["Resized", "resample", "resize_frame", "to_uint8"]


@dataclass(frozen=True)
class Resized:
    """A frame at model input size and the exact map from the source's pixels to it.

    ``image``: uint8 [h, w, 3] RGB (a new array, never a view of the caller's).
    ``transform``: source pixel (u, v) -> ``image`` pixel, centres at integers
    (``transform.apply_to_K(K)`` gives the intrinsics of ``image``).
    ``source_size``: (H, W) of the frame ``transform`` starts from (the pushed frame, before any
    object crop).
    """

    image: np.ndarray
    transform: PixelTransform
    source_size: Size

    @property
    def size(self) -> Size:
        return int(self.image.shape[0]), int(self.image.shape[1])


def _opencv_dtype(image: np.ndarray) -> np.ndarray:
    """``image`` in a dtype ``cv2.resize`` accepts (float16 is widened; others pass as they are)."""
    if image.dtype == np.float16:
        return image.astype(np.float32)
    return image


def resample(image: np.ndarray, plan: tuple[ResizeStep, ...]) -> np.ndarray:
    """``image`` [H, W(, C)] through every step of ``plan`` (no copy for an empty plan)."""
    out = _opencv_dtype(image) if plan else image
    for step in plan:
        height, width = step.size
        out = cv2.resize(out, (width, height), interpolation=step.interpolation)
    return out


def to_uint8(image: np.ndarray) -> np.ndarray:
    """uint8 RGB from uint8 (returned as is) or float in [0, 1] (rounded: k/255 maps back to k).

    Call it on frames at model size: it makes float32 temporaries of the whole input.
    """
    if image.dtype == np.uint8:
        return image
    scaled = np.clip(image.astype(np.float32), 0.0, 1.0)
    scaled *= 255.0
    return np.rint(scaled, out=scaled).astype(np.uint8)


def resize_frame(
    image: np.ndarray,
    plan: tuple[ResizeStep, ...],
    *,
    before: PixelTransform | None = None,
    source_size: Size | None = None,
) -> Resized:
    """``image`` (uint8, or float in [0, 1]) through ``plan``, as a uint8 ``Resized``.

    ``before``: the transform that produced ``image`` from the original frame (an object crop),
    composed into the result; ``source_size``: that original frame's (H, W) (default: this
    image's).
    """
    height, width = int(image.shape[0]), int(image.shape[1])
    out_size = plan_output_size((height, width), plan)
    resized = to_uint8(resample(image, plan))
    if np.may_share_memory(resized, image):
        resized = resized.copy()  # keyframes freeze their image: never freeze the user's array
    transform = PixelTransform.resize((height, width), out_size)
    if before is not None:
        transform = before.then(transform)
    return Resized(
        np.ascontiguousarray(resized), transform, source_size or (height, width)
    )

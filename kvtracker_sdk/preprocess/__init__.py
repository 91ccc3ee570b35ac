"""Preprocessing of frames, masks and boxes to a model's input, per model family (layer 0).

numpy + OpenCV only. ``for_family("pi3")`` / ``for_family("da3")`` give the pipeline equal to
that family's official one (``families``); sizing plans live in ``sizing``, resampling and the
float-frame path in ``resampling``, masks and object boxes in ``masks``. Every resize returns a
:class:`Resized`: the uint8 image, the exact :class:`~kvtracker_sdk.geometry.pixel_transform.PixelTransform` from
the pushed frame's pixels to it, and the pushed frame's size.
"""

from kvtracker_sdk.preprocess.families import (
    DA3_UPPER_BOUND,
    FAMILY_PREPROCESSING,
    LEGACY_AREA_FLOOR,
    PI3_KVTRACKER,
    PREPROCESSINGS,
    Preprocessing,
    for_family,
    named,
    register_family,
)
from kvtracker_sdk.preprocess.masks import BBox, MaskResampling, box_mask, fit_box, mask_bounds
from kvtracker_sdk.preprocess.resampling import Resized, to_uint8
from kvtracker_sdk.preprocess.sizing import (
    ResizeStep,
    da3_upper_bound_plan,
    legacy_area_floor_plan,
    pi3_kvtracker_plan,
)

__all__ = [
    "DA3_UPPER_BOUND",
    "FAMILY_PREPROCESSING",
    "LEGACY_AREA_FLOOR",
    "PI3_KVTRACKER",
    "PREPROCESSINGS",
    "BBox",
    "MaskResampling",
    "Preprocessing",
    "ResizeStep",
    "Resized",
    "box_mask",
    "da3_upper_bound_plan",
    "fit_box",
    "for_family",
    "legacy_area_floor_plan",
    "mask_bounds",
    "named",
    "pi3_kvtracker_plan",
    "register_family",
    "to_uint8",
]

"""Which preprocessing each model family gets, looked up by name (no branching on families).

A :class:`Preprocessing` bundles a sizing plan, the filter of a single resize (object crops go
straight to the model size), the mask resampling, and the resolution a family uses when the
config does not choose one. Its ``name`` is recorded in every saved map, so a loaded map's
frames can be prepared the way its keyframes were.

``FAMILY_PREPROCESSING`` maps a backend family (``BackendInfo.family``) to the name of its
preprocessing; ``PREPROCESSINGS`` maps names to definitions. Both are read-only views: a family
defined outside the package (an app's own backend) is added with :func:`register_family`, or its
backend declares a ``preprocessing`` attribute (``backends/base.py``).

What "resolution" (the config's side d) means:

* Pi3 (``pi3-kvtracker-v1``): the pixel budget, at most d² pixels (KV-Tracker: 224, 308, 518;
  default 308, its real-time setting). A 640x480 frame at 224 becomes 196x252.
* DA3 (``da3-upper-bound-v1``): the longest side (DA3's ``process_res``; default 504, DA3's own).
  A 640x480 frame at 504 becomes 378x504.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType

import cv2
import numpy as np

from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.geometry.pixel_transform import PixelTransform
from kvtracker_sdk.preprocess.masks import MaskResampling, resize_mask
from kvtracker_sdk.preprocess.resampling import Resized, resize_frame
from kvtracker_sdk.preprocess.sizing import (
    ResizeStep,
    Size,
    da3_upper_bound_plan,
    legacy_area_floor_plan,
    pi3_kvtracker_plan,
    plan_output_size,
)

__all__ = [
    "DA3_UPPER_BOUND",
    "FAMILY_PREPROCESSING",
    "LEGACY_AREA_FLOOR",
    "PI3_KVTRACKER",
    "PREPROCESSINGS",
    "Preprocessing",
    "for_family",
    "named",
    "register_family",
]

Plan = Callable[[Size, int, int], tuple[ResizeStep, ...]]  # (source, side, patch) -> steps
Filter = Callable[[Size, Size], int]  # (source, target) -> cv2.INTER_* of one resize


@dataclass(frozen=True)
class Preprocessing:
    """One family's way from a pushed frame to the model input (see the module docstring)."""

    name: str  # recorded in map headers; bump the suffix on any change of output pixels
    default_resolution: int
    plan: Plan
    single_step_filter: Filter
    mask_resampling: MaskResampling

    def model_size(self, source: Size, resolution: int, patch_size: int) -> Size:
        """(h, w) of the model input for a frame of ``source`` = (H, W)."""
        return plan_output_size(source, self.plan(source, resolution, patch_size))

    def resize(self, image: np.ndarray, resolution: int, patch_size: int) -> Resized:
        """The whole frame [H, W, 3] (uint8 or float in [0, 1]) at model size, as uint8."""
        source = (int(image.shape[0]), int(image.shape[1]))
        return resize_frame(image, self.plan(source, resolution, patch_size))

    def resize_crop(
        self, image: np.ndarray, window: tuple[int, int, int, int], size: Size
    ) -> Resized:
        """The crop ``window`` = (x0, y0, x1, y1) of ``image`` resized to ``size`` in one step;
        the transform maps pixels of the whole ``image``."""
        x0, y0, x1, y1 = window
        crop = image[y0:y1, x0:x1]
        crop_size = (y1 - y0, x1 - x0)
        plan = () if crop_size == size else (ResizeStep(size, self.single_step_filter(crop_size, size)),)
        source = (int(image.shape[0]), int(image.shape[1]))
        return resize_frame(crop, plan, before=PixelTransform.crop(x0, y0), source_size=source)

    def resize_mask(self, mask: np.ndarray, size: Size) -> np.ndarray:
        """A bool mask [H, W] resized to ``size`` the way this pipeline resizes masks."""
        return resize_mask(mask, size, self.mask_resampling)


def _area_down_cubic_up(source: Size, target: Size) -> int:
    """DA3's rule: cubic if either side grows, area otherwise."""
    grows = target[0] > source[0] or target[1] > source[1]
    return cv2.INTER_CUBIC if grows else cv2.INTER_AREA


def _by_pixel_count(source: Size, target: Size) -> int:
    """The legacy rule: area when the pixel count shrinks, cubic otherwise."""
    return cv2.INTER_AREA if target[0] * target[1] < source[0] * source[1] else cv2.INTER_CUBIC


PI3_KVTRACKER = Preprocessing(
    name="pi3-kvtracker-v1",
    default_resolution=308,
    plan=pi3_kvtracker_plan,
    single_step_filter=lambda source, target: cv2.INTER_LINEAR,
    mask_resampling=MaskResampling.BILINEAR_ANY,
)
DA3_UPPER_BOUND = Preprocessing(
    name="da3-upper-bound-v1",
    default_resolution=504,
    plan=da3_upper_bound_plan,
    single_step_filter=_area_down_cubic_up,
    # DA3 has no masks of its own: the KV-Tracker rule, which keeps every touched pixel
    mask_resampling=MaskResampling.BILINEAR_ANY,
)
LEGACY_AREA_FLOOR = Preprocessing(
    name="legacy-area-floor",
    default_resolution=308,
    plan=legacy_area_floor_plan,
    single_step_filter=_by_pixel_count,
    mask_resampling=MaskResampling.NEAREST,
)

_BUILT_IN = (PI3_KVTRACKER, DA3_UPPER_BOUND, LEGACY_AREA_FLOOR)
_preprocessings: dict[str, Preprocessing] = {p.name: p for p in _BUILT_IN}
_family_preprocessing: dict[str, str] = {
    "pi3": PI3_KVTRACKER.name,
    "da3": DA3_UPPER_BOUND.name,
    # the simulated backend stands in for the paper's model (Pi3)
    "simulated": PI3_KVTRACKER.name,
}
_BUILT_IN_FAMILIES = frozenset(_family_preprocessing)
_registry_lock = threading.Lock()  # registrations may come from any thread of an app

# read-only views: they show every registration, and only register_family changes them
PREPROCESSINGS: Mapping[str, Preprocessing] = MappingProxyType(_preprocessings)
FAMILY_PREPROCESSING: Mapping[str, str] = MappingProxyType(_family_preprocessing)


def register_family(family: str, preprocessing: Preprocessing | str = PI3_KVTRACKER) -> None:
    """Prepare the frames of model family ``family`` (``BackendInfo.family``) with
    ``preprocessing``: a :class:`Preprocessing` of the app's own, or a known one's name.

    Registering the same pair again is a no-op, so an app may call it at every start. Raises
    ConfigError for an empty family name, a built-in family, a family already registered with
    another preprocessing, or a new preprocessing whose name a different definition holds (the
    name is what saved maps record, so it must mean one pipeline).
    """
    if not isinstance(family, str) or not family:
        raise ConfigError(f"a model family needs a non-empty name, got {family!r}")
    with _registry_lock:
        if isinstance(preprocessing, str):
            definition = _preprocessings.get(preprocessing)
            if definition is None:
                raise ConfigError(f"unknown preprocessing {preprocessing!r} "
                                  f"(known: {sorted(_preprocessings)})")
        elif isinstance(preprocessing, Preprocessing):
            definition = preprocessing
            held = _preprocessings.get(definition.name)
            if held is not None and held != definition:
                raise ConfigError(f"preprocessing name {definition.name!r} is taken by another "
                                  "definition; give yours its own name")
        else:
            raise ConfigError(f"preprocessing must be a Preprocessing or a name, got "
                              f"{type(preprocessing).__name__}")
        current = _family_preprocessing.get(family)
        if current == definition.name:
            _preprocessings.setdefault(definition.name, definition)
            return
        if family in _BUILT_IN_FAMILIES or current is not None:
            raise ConfigError(f"model family {family!r} is already registered with "
                              f"preprocessing {current!r}")
        _preprocessings.setdefault(definition.name, definition)
        _family_preprocessing[family] = definition.name


def named(name: str) -> Preprocessing:
    """The preprocessing called ``name`` (as recorded in a map header), or ConfigError."""
    try:
        return PREPROCESSINGS[name]
    except KeyError:
        raise ConfigError(
            f"unknown preprocessing {name!r} (known: {sorted(PREPROCESSINGS)}); "
            "the map may come from a newer kvtracker-sdk"
        ) from None


def for_family(family: str) -> Preprocessing:
    """The preprocessing of the model family ``family`` ("pi3", "da3", ...), or ConfigError."""
    try:
        return PREPROCESSINGS[FAMILY_PREPROCESSING[family]]
    except KeyError:
        raise ConfigError(
            f"no preprocessing is registered for model family {family!r} "
            f"(known: {sorted(FAMILY_PREPROCESSING)}): call "
            "kvtracker_sdk.preprocess.register_family(family, preprocessing) once, or give the "
            "backend a 'preprocessing' attribute (docs/backends.md)"
        ) from None

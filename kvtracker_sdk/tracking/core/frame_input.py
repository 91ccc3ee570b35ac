"""Validation and preprocessing of the frames, masks and boxes a user pushes.

Everything here is checked before the tracker changes anything, so a bad frame raises a typed
:class:`~kvtracker_sdk.errors.InputError` and leaves the tracker, its map and its cache untouched.

Accepted input (design doc, "Per-frame result"):

* ``image``: numpy [H, W, 3] RGB, uint8 or a float dtype with values in [0, 1]; H, W >= the
  model's patch size; the same H, W for the whole session.
* ``mask``: numpy [H, W] (or [H, W, 1]) bool or integer (non-zero = object), selecting at least
  one pixel, also after resizing to the model resolution.
* ``bbox``: (x0, y0, x1, y1) in pixels of the image, x0 < x1, y0 < y1, inside [0, W] x [0, H].
  In object mode the ``Tracker`` passes the region it predicted (``object_region``) for a frame
  pushed without either, so only a frame with no region known yet lacks one (``MaskError``).
  Alone it acts as a rectangular mask; with a mask, the mask selects the object and the box only
  sets the crop region.

* ``camera``: the input image's intrinsics (``Camera`` of size W x H), optional. With OpenCV
  distortion the frame is undistorted first (same size and K), and the prepared frame's camera is
  the undistorted one.

Output: a uint8 image at model resolution, prepared by the model family's preprocessing
(``kvtracker_sdk.preprocess``: Pi3 as KV-Tracker, DA3 as its own input processor), or by the
loaded map's when it was made by another one; in object mode either the background blacked out
(``ObjectPreprocessing.MASK``) or a crop around the object dilated by ``crop_margin_px`` pixels of
the pushed frame and grown to the model's aspect ratio (``CROP``). The prepared frame carries the
exact pixel transform from the pushed frame to it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from kvtracker_sdk.config import ObjectPreprocessing, TrackerConfig, TrackingMode
from kvtracker_sdk.errors import (
    BBoxError,
    ConfigError,
    ImageDtypeError,
    ImageShapeError,
    InputError,
    MaskError,
    NonFiniteImageError,
    ResolutionChangedError,
)
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.geometry.pixel_transform import PixelTransform
from kvtracker_sdk.preprocess import (
    BBox,
    Preprocessing,
    box_mask,
    fit_box,
    for_family,
    mask_bounds,
    named,
)
from kvtracker_sdk.preprocess.undistort import Undistorter

__all__ = [
    "FramePreparer",
    "PreparedFrame",
    "check_bbox",
    "check_image",
    "check_mask",
    "check_time_order",
    "family_preprocessing",
    "resolve_resolution",
    "to_rgb",
]

# the channel orders push_frame/submit accept: "bgr" is what cv2.imread and VideoCapture give
COLOR_ORDERS = ("rgb", "bgr")


@dataclass(frozen=True)
class PreparedFrame:
    """A validated frame at model resolution, ready for a backend."""

    image: np.ndarray  # uint8 [h, w, 3] RGB at model resolution (object mode: masked or cropped)
    mask: np.ndarray | None  # bool [h, w] at model resolution, None when none was given
    input_size: tuple[int, int]  # (H, W) of the pushed image
    timestamp: float | None
    transform: PixelTransform  # pushed image pixel -> ``image`` pixel (crop and resize)
    preprocessing: str  # name of the preprocessing that made ``image`` (recorded in maps)
    camera: Camera | None = None  # the given intrinsics of the input image, undistorted
    depth: np.ndarray | None = None  # float32 [h, w] sensor depth, metres, model image (0 = hole)


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
    # min/max propagate NaN and expose inf without a full-size temporary (np.isfinite makes one)
    low, high = float(image.min()), float(image.max())
    if not (math.isfinite(low) and math.isfinite(high)):
        raise NonFiniteImageError("image contains NaN or infinite values")
    if low < 0.0 or high > 1.0:
        raise ImageDtypeError(f"float image values must lie in [0, 1], got [{low:g}, {high:g}]")
    return image


def to_rgb(image: Any, color: Any) -> Any:
    """``image`` in RGB order: a ``color="bgr"`` HxWx3 array (OpenCV's order) is flipped into a
    new contiguous array; anything else is returned as is for ``check_image`` to judge."""
    if color not in COLOR_ORDERS:
        raise InputError(f'color must be "rgb" or "bgr", got {str(color)[:40]!r}')
    if color == "bgr" and isinstance(image, np.ndarray) and image.ndim == 3 and image.shape[2] == 3:
        return np.ascontiguousarray(image[..., ::-1])
    return image


def check_time_order(timestamp: float | None, previous: float | None) -> None:
    """Timestamps of a session never go backwards (TUM/evo association and the trajectory
    files assume time order): InputError naming both. Equal stamps and None are accepted."""
    if timestamp is not None and previous is not None and timestamp < previous:
        raise InputError(
            f"timestamp {timestamp!r} is earlier than the previous frame's {previous!r}: "
            "timestamps must not go backwards within a session (reset() starts a new one)"
        )


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


def _check_size_and_camera(
    size: tuple[int, int], session_input_size: tuple[int, int] | None, camera: Any
) -> None:
    """The frame (H, W) ``size`` must be the session's, and a given camera must describe it."""
    if session_input_size is not None and size != tuple(session_input_size):
        raise ResolutionChangedError(
            f"image size changed from {tuple(session_input_size)} to {size} in mid-session; "
            "call reset() to start a session at the new size"
        )
    if camera is not None and not isinstance(camera, Camera):
        raise InputError(f"camera must be a kvtracker_sdk.Camera, got {type(camera).__name__}")
    if camera is not None and camera.size != size:
        raise InputError(
            f"the camera describes {camera.height}x{camera.width} images, the frame is "
            f"{size[0]}x{size[1]}"
        )


def _check_timestamp(timestamp: Any) -> float | None:
    if timestamp is None:
        return None
    try:
        value = float(timestamp)
    except (TypeError, ValueError, OverflowError) as exc:  # OverflowError: int beyond float
        raise InputError(f"timestamp must be a number or None, got {str(timestamp)[:40]}") from exc
    if not math.isfinite(value):
        raise InputError(f"timestamp must be finite, got {value}")
    return value


def family_preprocessing(family: str, declared: Any = None) -> Preprocessing:
    """The preprocessing of a backend: the one it declares (its ``preprocessing`` attribute, a
    :class:`Preprocessing`), else the one registered for its ``family``; ConfigError if neither."""
    if declared is None:
        return for_family(family)
    if not isinstance(declared, Preprocessing):
        raise ConfigError(
            f"a backend's 'preprocessing' must be a kvtracker_sdk.preprocess.Preprocessing, got "
            f"{type(declared).__name__}"
        )
    return declared


def resolve_resolution(
    config: TrackerConfig, family: str, declared: Preprocessing | None = None
) -> TrackerConfig:
    """``config`` with its resolution set: unset (None) means the family's default (Pi3 308,
    DA3 504). Raises ConfigError for a family without a registered or declared preprocessing."""
    preprocessing = family_preprocessing(family, declared)
    if config.resolution is not None:
        return config
    return config.updated(resolution=preprocessing.default_resolution)


class FramePreparer:
    """Turns user frames into ``PreparedFrame``s for one tracker configuration.

    ``family``: the backend's model family, which picks the preprocessing of new maps (unless
    the backend ``declared`` its own); a frame for a loaded map made by another preprocessing is
    prepared with that map's (``prepare``).
    """

    def __init__(
        self, config: TrackerConfig, *, patch_size: int, family: str, declared: Any = None
    ) -> None:
        self.preprocessing: Preprocessing = family_preprocessing(family, declared)
        self.config = resolve_resolution(config, family, self.preprocessing)
        self.patch_size = int(patch_size)
        self._undistort = Undistorter()

    @property
    def resolution(self) -> int:
        """The side d of the model input (its meaning is the preprocessing's)."""
        assert self.config.resolution is not None  # resolved in __init__
        return self.config.resolution

    def pipeline(self, name: str | None) -> Preprocessing:
        """The preprocessing called ``name`` (None: this tracker's, for new maps); a declared one
        is found by its name too, registered or not."""
        if name is None or name == self.preprocessing.name:
            return self.preprocessing
        return named(name)

    def model_size(
        self, input_size: tuple[int, int], preprocessing: Preprocessing | None = None
    ) -> tuple[int, int]:
        """(h, w) at model resolution for an input of (H, W)."""
        pipeline = preprocessing or self.preprocessing
        return pipeline.model_size(input_size, self.resolution, self.patch_size)

    def prepare(
        self,
        image: Any,
        *,
        timestamp: Any = None,
        mask: Any = None,
        bbox: Any = None,
        session_input_size: tuple[int, int] | None = None,
        map_resolution: tuple[int, int] | None = None,
        map_preprocessing: str | None = None,
        camera: Camera | None = None,
    ) -> PreparedFrame:
        """Validate and convert one frame; raises an InputError subclass and changes nothing.

        ``session_input_size``: the (H, W) of the session's first frame (None: first frame).
        ``map_resolution``: the current map's model (h, w), which the frame must produce.
        ``map_preprocessing``: the name of the preprocessing that made the current map's frames
        (None: no map, use the family's). ``camera``: the frame's intrinsics (its size must be
        the image's); a camera with distortion has the frame undistorted first.
        """
        pipeline = self.pipeline(map_preprocessing)
        checked = check_image(image, min_side=self.patch_size)
        size = (int(checked.shape[0]), int(checked.shape[1]))
        _check_size_and_camera(size, session_input_size, camera)
        stamp = _check_timestamp(timestamp)
        object_mask = check_mask(mask, size) if mask is not None else None
        box = check_bbox(bbox, size) if bbox is not None else None
        if object_mask is None and box is not None:
            object_mask = box_mask(box, size)
        object_mode = self.config.mode is TrackingMode.OBJECT
        if object_mode and object_mask is None:
            raise MaskError(
                "object mode needs a mask or a bbox with the first frame (the tracker predicts "
                "the object's region in the frames after it)"
            )

        out_size = self.model_size(size, pipeline)
        if map_resolution is not None and out_size != tuple(map_resolution):
            raise ResolutionChangedError(
                f"frames of {size} give model input {out_size}, the map was built at "
                f"{tuple(map_resolution)}"
            )
        if camera is not None and camera.has_distortion:
            checked = self._undistort(checked, camera)  # same size and K, lens model removed
            camera = camera.undistorted()
        crop = self.config.object.preprocessing is ObjectPreprocessing.CROP
        resized, object_mask = self._resized(
            checked, pipeline, out_size, object_mask, box, crop=object_mode and crop)
        small_mask = pipeline.resize_mask(object_mask, out_size) if object_mask is not None else None
        if small_mask is not None and not small_mask.any():
            raise MaskError(f"the mask is too small: it selects no pixel at model size {out_size}")
        image_out = resized.image  # a new array: never the caller's
        if object_mode and not crop and small_mask is not None:
            image_out[~small_mask] = 0  # black background (KV-Tracker object mode)
        return PreparedFrame(
            image_out, small_mask, size, stamp, resized.transform, pipeline.name, camera
        )

    def _resized(
        self, checked: np.ndarray, pipeline: Any, out_size: tuple[int, int],
        object_mask: np.ndarray | None, box: Any, *, crop: bool,
    ) -> tuple[Any, np.ndarray | None]:
        """The frame at model size, and the object mask in the same window: a crop around the
        object (object mode with crops, when a mask is known), else the whole frame resized."""
        if not (crop and object_mask is not None):
            return pipeline.resize(checked, self.resolution, self.patch_size), object_mask
        size = (int(checked.shape[0]), int(checked.shape[1]))
        window = fit_box(
            box if box is not None else mask_bounds(object_mask),
            size,
            margin=self.config.object.crop_margin_px,  # pixels of the pushed frame
            aspect=out_size[0] / out_size[1],
        )
        x0, y0, x1, y1 = window
        return pipeline.resize_crop(checked, window, out_size), object_mask[y0:y1, x0:x1]

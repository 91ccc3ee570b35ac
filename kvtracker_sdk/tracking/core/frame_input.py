"""What an app pushes with a frame, checked: the single entry of a frame into the tracker.

``check_frame`` checks everything ``push_frame`` (or ``submit``) was given, before the tracker
changes anything or asks anyone (the object region, the app's segmenter, the network) about the
frame, and hands on the checked values as one ``FrameInput``: a bad frame raises a typed
:class:`~kvtracker_sdk.errors.InputError` and leaves the tracker, its map and its cache untouched.
Turning the checked frame into the model's input is ``model_input``'s.

Accepted input (design doc, "Per-frame result"):

* ``image``: numpy [H, W, 3], uint8 or a float dtype with values in [0, 1]; H, W >= the
  model's patch size; the same H, W for the whole session. RGB, or BGR with ``color="bgr"``.
* ``timestamp``: seconds on any clock, finite, never earlier than the session's previous frame's.
* ``mask``: numpy [H, W] (or [H, W, 1]) bool or integer (non-zero = object), selecting at least
  one pixel (``model_input`` checks it still does at model resolution).
* ``bbox``: (x0, y0, x1, y1) in pixels of the image, x0 < x1, y0 < y1, inside [0, W] x [0, H].
  Alone it acts as a rectangular mask; with a mask, the mask selects the object and the box only
  sets the crop region. In object mode a frame pushed without either takes the region the
  tracker predicts (``tracking/object``).
* ``camera``: the input image's intrinsics (``Camera`` of size W x H), optional.
* ``depth``: an RGB-D sensor's depth image registered to ``image`` (same H, W: pixel (u, v) of
  both sees the same ray), either float (metres; ``depth_scale`` omitted, or a factor to metres)
  or integer raw units with ``depth_scale`` = metres per unit (RealSense 0.001, TUM's 16-bit PNGs
  1/5000, Kinect for Azure 0.001). Invalid pixels are 0 (NaN and inf are taken as invalid too:
  several SDKs mark holes so); a negative depth is a ``DepthError``: it is a wrong sign or a wrong
  dtype, not a hole.
* ``gravity``: gravity's direction in the frame's camera (3 numbers, pointing down, any length).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from kvtracker_sdk.errors import (
    BBoxError,
    DepthError,
    GravityError,
    ImageDtypeError,
    ImageShapeError,
    InputError,
    NonFiniteImageError,
    ResolutionChangedError,
)
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.preprocess import BBox
from kvtracker_sdk.tracking.core.object_masks import check_mask

__all__ = [
    "FrameInput",
    "check_bbox",
    "check_camera",
    "check_depth",
    "check_frame",
    "check_gravity",
    "check_image",
    "check_time_order",
    "to_rgb",
]

# the channel orders push_frame/submit accept: "bgr" is what cv2.imread and VideoCapture give
COLOR_ORDERS = ("rgb", "bgr")


@dataclass(frozen=True)
class FrameInput:
    """One pushed frame after every check, in the pixels of the pushed image (H, W)."""

    image: np.ndarray  # [H, W, 3] RGB, uint8 or float in [0, 1]: the caller's array unless flipped
    size: tuple[int, int]  # (H, W)
    timestamp: float | None
    mask: np.ndarray | None  # bool [H, W] the app gave (None: none)
    box: BBox | None  # (x0, y0, x1, y1) the app gave (None: none)
    camera: Camera | None  # the frame's intrinsics (given for it, else the session's), as given
    depth: np.ndarray | None  # float32 [H, W] sensor depth, metres (0 = invalid)
    gravity: np.ndarray | None  # float64 [3], camera frame, pointing down

    @property
    def given(self) -> bool:
        """The app gave the object's region with this frame (a mask or a box)."""
        return self.mask is not None or self.box is not None


def check_frame(
    image: Any, *, min_side: int, color: Any = "rgb", timestamp: Any = None, mask: Any = None,
    bbox: Any = None, camera: Any = None, depth: Any = None, depth_scale: Any = None,
    gravity: Any = None, session_size: tuple[int, int] | None = None,
    previous_timestamp: float | None = None,
) -> FrameInput:
    """Every value pushed with one frame, checked, or a typed InputError (nothing else happens).

    ``min_side``: the model's patch size; ``session_size``: the (H, W) of the session's frames
    (None: this is its first); ``previous_timestamp``: the session's last frame's stamp.
    """
    rgb = to_rgb(image, color)
    frame_camera = check_camera(camera)
    checked = check_image(rgb, min_side=min_side)
    size = (int(checked.shape[0]), int(checked.shape[1]))
    _check_size_and_camera(size, session_size, frame_camera)
    stamp = _check_timestamp(timestamp)
    object_mask = check_mask(mask, size) if mask is not None else None
    box = check_bbox(bbox, size) if bbox is not None else None
    check_time_order(stamp, previous_timestamp)
    metres = check_depth(depth, depth_scale, size) if depth is not None else None
    return FrameInput(checked, size, stamp, object_mask, box, frame_camera, metres,
                      check_gravity(gravity))


def check_camera(camera: Any) -> Camera | None:
    """``camera`` if it is a ``Camera`` or None, else InputError."""
    if camera is not None and not isinstance(camera, Camera):
        raise InputError(f"camera must be a kvtracker_sdk.Camera or None, got {camera!r}")
    return camera


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
    size: tuple[int, int], session_size: tuple[int, int] | None, camera: Camera | None
) -> None:
    """The frame (H, W) ``size`` must be the session's, and a given camera must describe it."""
    if session_size is not None and size != tuple(session_size):
        raise ResolutionChangedError(
            f"image size changed from {tuple(session_size)} to {size} in mid-session; "
            "call reset() to start a session at the new size"
        )
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


def _checked_scale(depth_scale: Any, *, required: bool) -> float:
    if depth_scale is None:
        if required:
            raise DepthError(
                "an integer depth image needs depth_scale (metres per unit, e.g. 0.001 for "
                "millimetres, 1/5000 for TUM PNGs); float depth is taken as metres"
            )
        return 1.0
    try:
        scale = float(depth_scale)
    except (TypeError, ValueError, OverflowError) as exc:
        raise DepthError(f"depth_scale must be a number, got {str(depth_scale)[:40]}") from exc
    if not (math.isfinite(scale) and scale > 0):
        raise DepthError(f"depth_scale must be finite and > 0 (metres per unit), got {scale}")
    return scale


def check_depth(depth: Any, depth_scale: Any, size: tuple[int, int]) -> np.ndarray:
    """float32 [H, W] metres (0 = invalid) of a depth image for a colour image of ``size``
    (H, W); raises ``DepthError`` and changes nothing otherwise."""
    if not isinstance(depth, np.ndarray):
        raise DepthError(f"depth must be a numpy array, got {type(depth).__name__}")
    if depth.ndim == 3 and depth.shape[2] == 1:
        depth = depth[..., 0]
    if depth.shape != tuple(size):
        raise DepthError(
            f"depth shape {depth.shape} does not match the colour image's {tuple(size)}: "
            "register the depth to the colour camera first"
        )
    if np.issubdtype(depth.dtype, np.integer) or depth.dtype == np.bool_:
        if depth.dtype == np.bool_:
            raise DepthError("depth must be numbers (raw units or metres), got a bool array")
        scale = _checked_scale(depth_scale, required=True)
        if depth.dtype.kind == "i" and depth.min() < 0:
            raise DepthError("depth has negative values (invalid pixels must be 0)")
        return (depth.astype(np.float64) * scale).astype(np.float32)
    if not np.issubdtype(depth.dtype, np.floating):
        raise DepthError(f"depth dtype must be integer (raw) or float (metres), got {depth.dtype}")
    scale = _checked_scale(depth_scale, required=False)
    metres = np.asarray(depth, dtype=np.float64) * scale
    valid = np.isfinite(metres)
    if (metres[valid] < 0).any():
        raise DepthError("depth has negative values (invalid pixels must be 0)")
    out = np.where(valid, metres, 0.0).astype(np.float32)
    if not np.isfinite(out).all():  # a finite float64 beyond float32's range
        raise DepthError("depth values overflow float32 metres: check depth_scale")
    return out


def check_gravity(gravity: Any) -> np.ndarray | None:
    """The gravity vector as float64 [3] (camera frame, pointing down), or GravityError."""
    if gravity is None:
        return None
    try:
        vector = np.asarray(gravity, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise GravityError(f"gravity must be 3 numbers, got {str(gravity)[:60]}") from exc
    if vector.shape != (3,) or not np.isfinite(vector).all():
        raise GravityError(f"gravity must be 3 finite numbers (camera frame), got {vector!r}")
    if float(np.linalg.norm(vector)) < 1e-6:
        raise GravityError("gravity is (nearly) zero: it must give a direction")
    return vector

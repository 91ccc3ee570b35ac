"""The checked frame as the model takes it: at model resolution, in the family's preprocessing.

``FramePreparer.to_model`` turns a ``FrameInput`` (``frame_input``: the pushed frame, checked)
and the mask it is prepared with into a ``PreparedFrame``: a uint8 image at model resolution,
prepared by the model family's preprocessing (``kvtracker_sdk.preprocess``: Pi3 as KV-Tracker,
DA3 as its own input processor), or by the loaded map's when it was made by another one. A
camera with OpenCV distortion has the frame undistorted first (same size and K; the prepared
frame's camera is the undistorted one). In object mode either the background is blacked out
(``ObjectPreprocessing.MASK``) or the frame is cropped around the object, dilated by
``crop_margin_px`` pixels of the pushed frame and grown to the model's aspect ratio (``CROP``).
The prepared frame carries the exact pixel transform from the pushed frame to it, and the sensor
depth resampled through it.

What can only be judged here raises a typed ``InputError`` before the tracker changes anything:
an object-mode frame with no region at all, a frame that does not give the map's model size, a
mask that selects no pixel at model resolution.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from kvtracker_sdk.config import ObjectPreprocessing, TrackerConfig, TrackingMode
from kvtracker_sdk.errors import ConfigError, MaskError, ResolutionChangedError
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.geometry.pixel_transform import PixelTransform
from kvtracker_sdk.preprocess import (
    Preprocessing,
    box_mask,
    fit_box,
    for_family,
    mask_bounds,
    named,
)
from kvtracker_sdk.preprocess.undistort import Undistorter
from kvtracker_sdk.tracking.core.frame_input import FrameInput, check_frame

__all__ = [
    "FramePreparer",
    "PreparedFrame",
    "depth_to_model",
    "family_preprocessing",
    "resolve_resolution",
]


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
    """Turns checked frames (``FrameInput``) into ``PreparedFrame``s for one tracker
    configuration.

    ``family``: the backend's model family, which picks the preprocessing of new maps (unless
    the backend ``declared`` its own); a frame for a loaded map made by another preprocessing is
    prepared with that map's (``to_model``).
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
        """Check and convert one frame as given (``check_frame``, then ``to_model`` with the
        frame's own mask or box); raises an InputError subclass and changes nothing.

        ``session_input_size``: the (H, W) of the session's first frame (None: first frame);
        the other arguments as in ``check_frame`` and ``to_model``.
        """
        frame = check_frame(image, min_side=self.patch_size, timestamp=timestamp, mask=mask,
                            bbox=bbox, camera=camera, session_size=session_input_size)
        return self.to_model(frame, frame.mask, map_resolution=map_resolution,
                             map_preprocessing=map_preprocessing)

    def to_model(
        self, frame: FrameInput, mask: np.ndarray | None, *,
        map_resolution: tuple[int, int] | None = None, map_preprocessing: str | None = None,
    ) -> PreparedFrame:
        """``frame`` prepared for the model with ``mask`` (bool [H, W]: the app's, or the region
        object mode chose; None: none, then ``frame.box`` alone acts as the mask).

        ``map_resolution``: the current map's model (h, w), which the frame must produce.
        ``map_preprocessing``: the name of the preprocessing that made the current map's frames
        (None: no map, use the family's). Raises an InputError subclass and changes nothing.
        """
        pipeline = self.pipeline(map_preprocessing)
        object_mode = self.config.mode is TrackingMode.OBJECT
        if mask is None and frame.box is not None:
            mask = box_mask(frame.box, frame.size)
        if object_mode and mask is None:
            raise MaskError(
                "object mode needs a mask or a bbox with the first frame (the tracker predicts "
                "the object's region in the frames after it)"
            )
        out_size = self.model_size(frame.size, pipeline)
        if map_resolution is not None and out_size != tuple(map_resolution):
            raise ResolutionChangedError(
                f"frames of {frame.size} give model input {out_size}, the map was built at "
                f"{tuple(map_resolution)}"
            )
        image, depth, camera = frame.image, frame.depth, frame.camera
        if camera is not None and camera.has_distortion:  # same size and K, lens model removed
            image = self._undistort(image, camera)
            if depth is not None:  # registered to the colour frame: undistorted alike
                depth = self._undistort(depth, camera, nearest=True)
            camera = camera.undistorted()
        crop = object_mode and self.config.object.preprocessing is ObjectPreprocessing.CROP
        resized, mask = self._resized(image, pipeline, out_size, mask, frame.box, crop=crop)
        small_mask = pipeline.resize_mask(mask, out_size) if mask is not None else None
        if small_mask is not None and not small_mask.any():
            raise MaskError(f"the mask is too small: it selects no pixel at model size {out_size}")
        image_out = resized.image  # a new array: never the caller's
        if object_mode and not crop and small_mask is not None:
            image_out[~small_mask] = 0  # black background (KV-Tracker object mode)
        if depth is not None:
            depth = depth_to_model(depth, resized.transform, image_out.shape[:2])
        return PreparedFrame(image_out, small_mask, frame.size, frame.timestamp,
                             resized.transform, pipeline.name, camera, depth)

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


def depth_to_model(
    depth: np.ndarray, transform: PixelTransform, out_size: tuple[int, int]
) -> np.ndarray:
    """float32 [h, w] depth of the model image (``out_size``) sampled from ``depth`` [H, W]
    (metres) through the prepared frame's pixel ``transform`` (input pixel -> model pixel).

    Nearest neighbour, on purpose: interpolating would average a foreground and a background
    depth at an edge into a depth where nothing is, and would blend valid pixels with holes (0).
    Model pixels whose source lies outside the input image (padding) are 0.
    """
    height, width = out_size
    back = transform.inverse()
    cols = np.rint(back.sx * np.arange(width) + back.ox).astype(np.int64)
    rows = np.rint(back.sy * np.arange(height) + back.oy).astype(np.int64)
    col_ok = (cols >= 0) & (cols < depth.shape[1])
    row_ok = (rows >= 0) & (rows < depth.shape[0])
    sampled = depth[np.clip(rows, 0, depth.shape[0] - 1)[:, None],
                    np.clip(cols, 0, depth.shape[1] - 1)[None, :]]
    sampled = np.where(row_ok[:, None] & col_ok[None, :], sampled, 0.0)
    return np.ascontiguousarray(sampled, dtype=np.float32)

"""Camera intrinsics from files and from datasets that publish them.

``read_camera_file(path)`` reads JSON (``.json``) or YAML (``.yaml``/``.yml``, needs PyYAML: the
``[yaml]`` extra) in any of three layouts:

* the SDK's own: ``{"fx", "fy", "cx", "cy", "width", "height", "distortion": [k1, k2, p1, p2, k3]}``
  (``Camera.to_dict``);
* a ROS ``sensor_msgs/CameraInfo`` message: ``width``, ``height``, ``distortion_model``, ``D``,
  ``K`` (9 numbers, row-major), optionally ``P`` (ROS 2 spells them ``d``/``k``/``p``);
* a ROS ``camera_calibration`` YAML: ``image_width``, ``image_height``, ``camera_matrix:
  {rows, cols, data}``, ``distortion_model``, ``distortion_coefficients: {data}``.

ROS distortion models ``plumb_bob`` and ``rational_polynomial`` are OpenCV's 5 and 8 coefficients;
``equidistant`` (fisheye) is refused. ``K`` is used, not ``P``: ``P`` describes the rectified
image, and the SDK undistorts with K itself (``preprocess/undistort.py``).

``DATASET_CAMERAS`` holds the published intrinsics of the TUM RGB-D cameras (fr1, fr2, fr3) and of
7-Scenes; ``io/sources.py`` attaches them to the sequences it opens.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from kvtracker_sdk.errors import InputError, MissingDependencyError, SourceError
from kvtracker_sdk.geometry.camera import Camera

__all__ = ["DATASET_CAMERAS", "camera_from_mapping", "read_camera_file"]

# https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats ("Intrinsic Camera Calibration");
# fr3 images are published already undistorted. 7-Scenes: the Kinect's default, 585 px focal.
DATASET_CAMERAS: dict[str, Camera] = {
    "tum_fr1": Camera(517.3, 516.5, 318.6, 255.3, 640, 480, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "tum_fr2": Camera(520.9, 521.0, 325.1, 249.7, 640, 480, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "tum_fr3": Camera(535.4, 539.2, 320.1, 247.6, 640, 480),
    "7scenes": Camera(585.0, 585.0, 320.0, 240.0, 640, 480),
}  # fmt: skip

_OPENCV_MODELS = {"plumb_bob", "rational_polynomial", "opencv", "radtan", ""}


def _field(data: Mapping[str, Any], *names: str) -> Any:
    for name in names:
        if name in data:
            return data[name]
    return None


def _numbers(value: Any, what: str) -> list[float]:
    if isinstance(value, Mapping):  # camera_calibration: {rows, cols, data}
        value = value.get("data")
    if not isinstance(value, list | tuple) or not all(isinstance(v, int | float) for v in value):
        raise InputError(f"camera {what} must be a list of numbers, got {value!r}")
    return [float(v) for v in value]


def camera_from_mapping(data: Mapping[str, Any], source: str = "camera") -> Camera:
    """A ``Camera`` from a parsed camera file (any of the layouts in the module docstring)."""
    if not isinstance(data, Mapping):
        raise InputError(f"{source}: a camera file must hold a mapping, got {type(data).__name__}")
    if "fx" in data:
        return Camera.from_dict(data)
    matrix = _field(data, "K", "k", "camera_matrix")
    width = _field(data, "width", "image_width")
    height = _field(data, "height", "image_height")
    if matrix is None or width is None or height is None:
        raise InputError(
            f"{source}: need fx/fy/cx/cy/width/height, a ROS CameraInfo (K, D, width, height) or "
            f"a camera_calibration file (camera_matrix, image_width, image_height); got keys "
            f"{sorted(data)}"
        )
    model = str(_field(data, "distortion_model") or "").lower()
    if model not in _OPENCV_MODELS:
        raise InputError(f"{source}: distortion model {model!r} is not OpenCV's pinhole model "
                         "(plumb_bob or rational_polynomial)")
    k = _numbers(matrix, "K")
    if len(k) != 9:
        raise InputError(f"{source}: K must have 9 numbers, got {len(k)}")
    distortion = _numbers(_field(data, "D", "d", "distortion_coefficients") or [], "D")
    try:
        return Camera.from_K(np.reshape(k, (3, 3)), int(width), int(height), distortion)
    except InputError as exc:
        raise InputError(f"{source}: {exc}") from exc


# what the CLI says to do about a camera file it cannot use (--camera FILE)
_CAMERA_FILE_HINT = ("--camera takes a JSON or YAML file with fx, fy, cx, cy, width, height "
                     "(pixels) and optional distortion, or a ROS CameraInfo's fields")


def read_camera_file(path: str | os.PathLike[str]) -> Camera:
    """The camera described by a JSON or YAML file (layouts: module docstring)."""
    target = Path(path)
    try:
        text = target.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SourceError(f"cannot read camera file {target}: {exc}", hint=_CAMERA_FILE_HINT) from exc
    if target.suffix.lower() in (".yaml", ".yml"):
        try:
            import yaml
        except ImportError as exc:
            raise MissingDependencyError.for_extra(
                "yaml", "reading a YAML camera file needs PyYAML (or write the camera as JSON)"
            ) from exc
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise SourceError(f"{target} is not valid YAML: {exc}", hint=_CAMERA_FILE_HINT) from exc
    else:
        try:
            data = json.loads(text)
        except ValueError as exc:
            raise SourceError(f"{target} is not valid JSON: {exc}", hint=_CAMERA_FILE_HINT) from exc
    return camera_from_mapping(data, str(target))

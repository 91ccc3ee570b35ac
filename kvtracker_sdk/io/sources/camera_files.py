"""Camera intrinsics from files and from datasets that publish them.

``read_camera_file(path)`` reads JSON (``.json``) or YAML (``.yaml``/``.yml``, needs PyYAML: the
``[yaml]`` extra) in any of three layouts:

* the SDK's own: ``{"fx", "fy", "cx", "cy", "width", "height", "distortion": [k1, k2, p1, p2, k3]}``
  (``Camera.to_dict``);
* a ROS ``sensor_msgs/CameraInfo`` message: ``width``, ``height``, ``distortion_model``, ``D``,
  ``K`` (9 numbers, row-major), optionally ``P`` (ROS 2 spells them ``d``/``k``/``p``);
* a ROS ``camera_calibration`` YAML: ``image_width``, ``image_height``, ``camera_matrix:
  {rows, cols, data}``, ``distortion_model``, ``distortion_coefficients: {data}``.

Every value is checked against a plausible range before a ``Camera`` is made (``SourceError``
naming the field): ``width``/``height`` whole numbers in [1, 65536] px; ``fx``/``fy`` in
[1e-3, 1e4] x the longer image side (fields of view from ~0.01 to ~179.9 degrees); ``cx``/``cy``
within one image size of the image; distortion coefficients finite with magnitude at most
``MAX_DISTORTION``. The file itself is read with ``io/user_files.py`` (regular files only, size
cap, bounded nesting, safe YAML with alias-bomb protection).

ROS distortion models ``plumb_bob`` and ``rational_polynomial`` are OpenCV's 5 and 8 coefficients;
``equidistant`` (fisheye) is refused. ``K`` is used, not ``P``: ``P`` describes the rectified
image, and the SDK undistorts with K itself (``preprocess/undistort.py``).

``DATASET_CAMERAS`` holds the published intrinsics of the TUM RGB-D cameras (fr1, fr2, fr3) and of
7-Scenes; ``io/sources/sources.py`` attaches them to the sequences it opens.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from kvtracker_sdk.errors import InputError, SourceError
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.user_files import checked_number, load_user_document

__all__ = [
    "DATASET_CAMERAS",
    "FOCAL_PER_SIDE",
    "MAX_DISTORTION",
    "MAX_IMAGE_SIDE",
    "camera_from_mapping",
    "read_camera_file",
]

MAX_IMAGE_SIDE = 65536  # px: larger than any camera sensor; also bounds undistortion maps
FOCAL_PER_SIDE = (1e-3, 1e4)  # focal length / longer image side: ~179.9 to ~0.006 degree FOV
# OpenCV's rational model fits coefficients up to a few hundred on real wide-angle lenses;
# larger ones describe no lens and make undistortion's fixed-point iteration diverge
MAX_DISTORTION = 1e3
_CAMERA_KEYS = 64  # a camera file has ~10 fields; ROS messages ~12

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


def _numbers(value: Any, what: str, source: str) -> list[float]:
    """A list of finite numbers (SourceError naming ``what`` otherwise)."""
    if isinstance(value, Mapping):  # camera_calibration: {rows, cols, data}
        value = value.get("data")
    if not isinstance(value, list | tuple) or len(value) > 16:
        raise SourceError(f"{source}: camera {what} must be a list of at most 16 numbers, "
                          f"got {type(value).__name__}")
    return [
        checked_number(v, f"{what}[{i}]", SourceError, low=-math.inf, high=math.inf,
                       source=source)
        for i, v in enumerate(value)
    ]


def camera_from_mapping(data: Mapping[str, Any], source: str = "camera") -> Camera:
    """A ``Camera`` from a parsed camera file (any of the layouts in the module docstring)."""
    if not isinstance(data, Mapping):
        raise SourceError(f"{source}: a camera file must hold a mapping, got {type(data).__name__}")
    if len(data) > _CAMERA_KEYS:
        raise SourceError(f"{source}: {len(data)} fields, more than a camera file has")
    if "fx" in data:
        missing = [name for name in ("fy", "cx", "cy", "width", "height") if name not in data]
        if missing:
            raise SourceError(f"{source}: camera needs fx, fy, cx, cy, width, height; missing {missing}")
        distortion = _numbers(data.get("distortion") or [], "distortion", source)
        return _checked_camera(
            source, data["fx"], data["fy"], data["cx"], data["cy"], data["width"], data["height"],
            distortion,
        )
    matrix = _field(data, "K", "k", "camera_matrix")
    width = _field(data, "width", "image_width")
    height = _field(data, "height", "image_height")
    if matrix is None or width is None or height is None:
        raise InputError(
            f"{source}: need fx/fy/cx/cy/width/height, a ROS CameraInfo (K, D, width, height) or "
            f"a camera_calibration file (camera_matrix, image_width, image_height); got keys "
            f"{sorted(str(key)[:40] for key in data)}"
        )
    raw_model = _field(data, "distortion_model") or ""
    model = raw_model.lower() if isinstance(raw_model, str) else repr(raw_model)[:40]
    if model not in _OPENCV_MODELS:
        raise InputError(f"{source}: distortion_model {model!r} is not OpenCV's pinhole model "
                         "(plumb_bob or rational_polynomial)")
    k = _numbers(matrix, "K", source)
    if len(k) != 9:
        raise InputError(f"{source}: K must have 9 numbers, got {len(k)}")
    distortion = _numbers(_field(data, "D", "d", "distortion_coefficients") or [], "D", source)
    matrix_3x3 = np.reshape(k, (3, 3))
    # no skew, last row [0, 0, 1]: Camera.from_K's check, on numbers already known finite
    if (abs(k[1]) > 1e-9 * abs(k[0]) or abs(k[3]) > 1e-12
            or not np.allclose(matrix_3x3[2], [0.0, 0.0, 1.0], atol=1e-12)):
        raise InputError(
            f"{source}: K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew), got {k}"
        )
    return _checked_camera(
        source, k[0], k[4], k[2], k[5], width, height, distortion,
    )


def _checked_camera(
    source: str, fx: Any, fy: Any, cx: Any, cy: Any, width: Any, height: Any,
    distortion: list[float],
) -> Camera:
    """A ``Camera`` from raw file values, each checked against its range (module docstring)."""
    w = int(checked_number(width, "width", SourceError, low=1, high=MAX_IMAGE_SIDE, integer=True,
                           source=source))
    h = int(checked_number(height, "height", SourceError, low=1, high=MAX_IMAGE_SIDE,
                           integer=True, source=source))
    side = max(w, h)
    low, high = FOCAL_PER_SIDE[0] * side, FOCAL_PER_SIDE[1] * side
    focal = [checked_number(f, name, SourceError, low=low, high=high, source=source)
             for name, f in (("fx", fx), ("fy", fy))]
    centre = [
        checked_number(cx, "cx", SourceError, low=-w, high=2.0 * w, source=source),
        checked_number(cy, "cy", SourceError, low=-h, high=2.0 * h, source=source),
    ]
    for index, coefficient in enumerate(distortion):
        checked_number(coefficient, f"distortion[{index}]", SourceError, low=-MAX_DISTORTION,
                       high=MAX_DISTORTION, source=source)
    try:
        return Camera(focal[0], focal[1], centre[0], centre[1], w, h, tuple(distortion))
    except InputError as exc:  # the distortion count
        raise SourceError(f"{source}: {exc}") from exc


# what the CLI says to do about a camera file it cannot use (--camera FILE)
_CAMERA_FILE_HINT = ("--camera takes a JSON or YAML file with fx, fy, cx, cy, width, height "
                     "(pixels) and optional distortion, or a ROS CameraInfo's fields")


def read_camera_file(path: str | os.PathLike[str]) -> Camera:
    """The camera described by a JSON or YAML file (layouts and checked ranges: module docstring).

    ``SourceError`` (naming the field) for a file that is not a regular file, too large, not
    JSON/YAML, or holds a value outside its range; ``MissingDependencyError`` for YAML without
    PyYAML."""
    document = load_user_document(path, SourceError, what="camera file")
    return camera_from_mapping(document, str(path))

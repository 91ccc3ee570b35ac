"""Intrinsics for the exporters (COLMAP, nerfstudio, ROS) when no calibration is known.

The exporters take the SDK's one camera type, :class:`~kvtracker_sdk.geometry.camera.Camera`
(``PinholeIntrinsics`` is its deprecated old name here, for one release). Pixel convention: the
SDK's (``geometry/pixel_transform.py``): integer coordinates are pixel centres, so the centre of
a W-pixel-wide image is at u = (W - 1) / 2. Each writer converts to its format's convention
itself (COLMAP and nerfstudio put the first pixel's centre at 0.5).

The network predicts geometry, not intrinsics: without a calibration, :func:`estimate_intrinsics`
fits one focal length to a keyframe's local points (principal point at the image centre).
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

from kvtracker_sdk.errors import InputError
from kvtracker_sdk.geometry.camera import Camera

__all__ = ["DEFAULT_FOCAL_PER_WIDTH", "estimate_intrinsics"]

DEFAULT_FOCAL_PER_WIDTH = 0.8  # ~64 degrees horizontal field of view: used without usable points


def __getattr__(name: str) -> Any:
    """``PinholeIntrinsics``: the old name of :class:`~kvtracker_sdk.geometry.camera.Camera`,
    kept for one release (a DeprecationWarning on use)."""
    if name == "PinholeIntrinsics":
        warnings.warn(
            "kvtracker_sdk PinholeIntrinsics is deprecated: use kvtracker_sdk.Camera (the same "
            "fields; K is the method Camera.K(), transformed() takes the (H, W) size)",
            DeprecationWarning, stacklevel=2,
        )
        return Camera
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def estimate_intrinsics(
    local_points: np.ndarray, confidence: np.ndarray | None = None, *, min_confidence: float = 0.5
) -> Camera:
    """One focal length (fx = fy) fitted to point maps, principal point at the image centre.

    ``local_points`` [H, W, 3] (or [N, H, W, 3] for N images of one camera, with ``confidence``
    [N, H, W]) are camera-frame points of each pixel (OpenCV axes). A pixel
    (u, v) sees (x, y, z) at u - cx = f x / z, v - cy = f y / z; f minimises the squared pixel
    residuals over the pixels with ``confidence >= min_confidence`` and z > 0. Without usable
    pixels f = ``DEFAULT_FOCAL_PER_WIDTH`` * W.
    """
    points = np.asarray(local_points, dtype=np.float64)
    if points.ndim not in (3, 4) or points.shape[-1] != 3:
        raise InputError(f"local points must be [H, W, 3] or [N, H, W, 3], got {points.shape}")
    height, width = points.shape[-3:-1]
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    v, u = np.mgrid[0:height, 0:width]
    offsets = np.stack([u - cx, v - cy], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        rays = points[..., :2] / points[..., 2:3]
    usable = (points[..., 2] > 0) & np.all(np.isfinite(rays), axis=-1)
    if confidence is not None:
        usable &= np.asarray(confidence) >= min_confidence
    a, b = rays[usable], np.broadcast_to(offsets, rays.shape)[usable]
    denominator = float(np.sum(a * a))
    focal = float(np.sum(a * b)) / denominator if denominator > 0 else 0.0
    if not (np.isfinite(focal) and focal > 0):
        focal = DEFAULT_FOCAL_PER_WIDTH * width
    return Camera(focal, focal, cx, cy, width, height)

"""``PinholeIntrinsics``: the camera model the exporters (COLMAP, nerfstudio, ROS) write.

Pixel convention: the SDK's (``geometry/pixel_transform.py``): integer coordinates are pixel
centres, so the centre of a W-pixel-wide image is at u = (W - 1) / 2. Each writer converts to
its format's convention itself (COLMAP and nerfstudio put the first pixel's centre at 0.5).

The network predicts geometry, not intrinsics: without a calibration, :func:`estimate_intrinsics`
fits one focal length to a keyframe's local points (principal point at the image centre).

Seam: until the SDK has a public camera type (``FrameResult.intrinsics``, in progress), this
dataclass is the exporters' input; it converts from any object with ``fx, fy, cx, cy, width,
height`` (:meth:`PinholeIntrinsics.of`), so the switch is one line per caller.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from kvtracker_sdk.errors import InputError
from kvtracker_sdk.geometry.pixel_transform import PixelTransform

__all__ = ["DEFAULT_FOCAL_PER_WIDTH", "PinholeIntrinsics", "estimate_intrinsics"]

DEFAULT_FOCAL_PER_WIDTH = 0.8  # ~64 degrees horizontal field of view: used without usable points


@dataclass(frozen=True)
class PinholeIntrinsics:
    """fx, fy, cx, cy in pixels (pixel centres at integers) for a ``width`` x ``height`` image."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        values = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(v) for v in values) or self.fx <= 0 or self.fy <= 0:
            raise InputError(f"intrinsics must be finite with positive focal lengths, got {values}")
        if int(self.width) < 1 or int(self.height) < 1:
            raise InputError(f"image size must be positive, got {self.width}x{self.height}")

    @classmethod
    def of(cls, camera: Any) -> PinholeIntrinsics:
        """From any object with ``fx, fy, cx, cy, width, height`` (e.g. the SDK's camera type)."""
        if isinstance(camera, PinholeIntrinsics):
            return camera
        return cls(float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy),
                   int(camera.width), int(camera.height))

    @classmethod
    def from_K(cls, K: np.ndarray, width: int, height: int) -> PinholeIntrinsics:
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), width, height)

    @property
    def K(self) -> np.ndarray:
        """3x3 float64 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def vertical_fov(self) -> float:
        """Vertical field of view in radians."""
        return float(2.0 * np.arctan2(self.height / 2.0, self.fy))

    def transformed(self, transform: PixelTransform, width: int, height: int) -> PinholeIntrinsics:
        """These intrinsics after the pixel map ``transform`` onto a ``width`` x ``height`` image."""
        return PinholeIntrinsics.from_K(transform.apply_to_K(self.K), width, height)

    def resized(self, width: int, height: int) -> PinholeIntrinsics:
        """These intrinsics for the image resized (``cv2.resize``) to ``width`` x ``height``."""
        transform = PixelTransform.resize((self.height, self.width), (height, width))
        return self.transformed(transform, width, height)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """[N, 3] camera-frame points (OpenCV axes) -> [N, 2] pixels (u, v)."""
        points = np.asarray(points_cam, dtype=np.float64)
        return np.stack([self.fx * points[:, 0] / points[:, 2] + self.cx,
                         self.fy * points[:, 1] / points[:, 2] + self.cy], axis=1)

    def rays(self) -> np.ndarray:
        """[H, W, 3] float64 ray of every pixel with z = 1 (camera frame, OpenCV axes)."""
        v, u = np.mgrid[0:self.height, 0:self.width].astype(np.float64)
        return np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], -1)


def estimate_intrinsics(
    local_points: np.ndarray, confidence: np.ndarray | None = None, *, min_confidence: float = 0.5
) -> PinholeIntrinsics:
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
    return PinholeIntrinsics(focal, focal, cx, cy, width, height)

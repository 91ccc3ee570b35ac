"""``Camera``: pinhole intrinsics of one image size, optional OpenCV distortion, and the
projection matrix a renderer needs. The SDK's one camera type: the tracker's input and results,
map files, camera files, and the exporters (COLMAP, nerfstudio, ROS) all take it.

Conventions (the same as every K in the SDK, and OpenCV's):

* Pixel coordinates (u, v): u to the right, v down, **integer values at pixel centres**; pixel
  (0, 0) covers [-0.5, 0.5]², the image spans [-0.5, W - 0.5] x [-0.5, H - 0.5].
* Camera axes: OpenCV (x right, y down, z forward). A point (X, Y, Z) with Z > 0 projects to
  ``u = fx X / Z + cx``, ``v = fy Y / Z + cy`` (before distortion).
* ``width``, ``height``: the size in pixels of the image these intrinsics describe. Intrinsics of
  another image of the same camera (resized, cropped) come from :meth:`Camera.transformed` with
  the :class:`~kvtracker_sdk.geometry.pixel_transform.PixelTransform` that made it.
* ``distortion``: OpenCV coefficients ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``; empty for none.
  The tracker undistorts such frames before the network (``preprocess/undistort.py``), after which
  the frame's intrinsics are :meth:`Camera.undistorted` (same K, no distortion).

Rendering: :meth:`Camera.projection_matrix` is the OpenGL projection (see its docstring) and
:func:`gl_view_matrix` the OpenGL view matrix of a ``T_world_cam`` pose.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from kvtracker_sdk.errors import InputError
from kvtracker_sdk.geometry.pixel_transform import PixelTransform

__all__ = ["Camera", "IntrinsicsSource", "gl_view_matrix"]

_DISTORTION_LENGTHS = (0, 4, 5, 8)
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera axes -> OpenGL eye axes


class IntrinsicsSource(str, enum.Enum):
    """Where a frame's intrinsics come from."""

    GIVEN = "given"  # passed by the app (per session or per frame), or read from the source
    PREDICTED = "predicted"  # the network predicts them (Depth Anything 3's camera decoder)
    ESTIMATED = "estimated"  # fitted to the network's local points by least squares (Pi3)


def _finite(value: Any, name: str) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"camera {name} must be a number, got {value!r}") from exc
    if not math.isfinite(number):
        raise InputError(f"camera {name} must be finite, got {number}")
    return number


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics (pixels) of a ``width`` x ``height`` image; see the module docstring."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, _finite(getattr(self, name), name))
        if self.fx <= 0 or self.fy <= 0:
            raise InputError(f"camera focal lengths must be > 0, got fx={self.fx}, fy={self.fy}")
        if int(self.width) != self.width or int(self.height) != self.height:
            raise InputError(f"camera size must be whole pixels, got {self.width}x{self.height}")
        if self.width < 1 or self.height < 1:
            raise InputError(f"camera size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        coefficients = tuple(_finite(c, "distortion") for c in self.distortion)
        if len(coefficients) not in _DISTORTION_LENGTHS:
            raise InputError(
                f"OpenCV distortion needs 4, 5 or 8 coefficients (k1, k2, p1, p2[, k3[, k4, k5, "
                f"k6]]), got {len(coefficients)}"
            )
        if not any(coefficients):
            coefficients = ()  # all zero: no distortion
        object.__setattr__(self, "distortion", coefficients)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_K(
        cls, K: np.ndarray, width: int, height: int, distortion: Sequence[float] = ()
    ) -> Camera:
        """From a 3x3 ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` (skew must be 0)."""
        matrix = np.asarray(K, dtype=np.float64)
        if matrix.shape != (3, 3):
            raise InputError(f"K must be 3x3, got shape {matrix.shape}")
        if abs(matrix[0, 1]) > 1e-9 * abs(matrix[0, 0]) or not np.allclose(
            matrix[2], [0.0, 0.0, 1.0], atol=1e-12
        ) or abs(matrix[1, 0]) > 1e-12:
            raise InputError(
                f"K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew), got {matrix.tolist()}"
            )
        return cls(
            float(matrix[0, 0]), float(matrix[1, 1]), float(matrix[0, 2]), float(matrix[1, 2]),
            width, height, tuple(float(d) for d in distortion),
        )

    @classmethod
    def of(cls, camera: Any) -> Camera:
        """From any object with ``fx, fy, cx, cy, width, height`` (and optionally
        ``distortion``): another library's camera type."""
        if isinstance(camera, Camera):
            return camera
        try:
            return cls(camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height,
                       tuple(getattr(camera, "distortion", ()) or ()))
        except AttributeError as exc:
            raise InputError(f"not a camera (needs fx, fy, cx, cy, width, height): {camera!r}") from exc

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Camera:
        """The inverse of :meth:`to_dict`."""
        try:
            return cls(
                data["fx"], data["fy"], data["cx"], data["cy"], data["width"], data["height"],
                tuple(data.get("distortion") or ()),
            )
        except (KeyError, TypeError) as exc:
            raise InputError(f"camera needs fx, fy, cx, cy, width, height; got {dict(data)}") from exc

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (floats written with repr read back bit for bit)."""
        return {
            "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
            "width": self.width, "height": self.height, "distortion": list(self.distortion),
        }  # fmt: skip

    # ------------------------------------------------------------------ views
    @property
    def size(self) -> tuple[int, int]:
        """(H, W) of the image, the SDK's order for image sizes."""
        return self.height, self.width

    @property
    def has_distortion(self) -> bool:
        return bool(self.distortion)

    def K(self) -> np.ndarray:
        """3x3 float64 intrinsic matrix."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    def fov_deg(self) -> tuple[float, float]:
        """(horizontal, vertical) field of view in degrees, edge to edge of the image."""
        left, right = self.cx + 0.5, self.width - 0.5 - self.cx
        top, bottom = self.cy + 0.5, self.height - 0.5 - self.cy
        horizontal = math.atan(left / self.fx) + math.atan(right / self.fx)
        vertical = math.atan(top / self.fy) + math.atan(bottom / self.fy)
        return math.degrees(horizontal), math.degrees(vertical)

    @property
    def vertical_fov(self) -> float:
        """Vertical field of view in radians, ``2 atan(H / 2 fy)`` (a centred principal point)."""
        return float(2.0 * math.atan2(self.height / 2.0, self.fy))

    def undistorted(self) -> Camera:
        """The camera of the undistorted image (same K and size, no distortion)."""
        return Camera(self.fx, self.fy, self.cx, self.cy, self.width, self.height)

    def transformed(self, transform: PixelTransform, size: tuple[int, int]) -> Camera:
        """Intrinsics of the image made by ``transform`` (resize/crop/pad) of size (H, W).

        Exact: ``K' = A K`` (``PixelTransform.apply_to_K``). Only for undistorted cameras: a
        lens model does not survive a crop's change of principal point in this form.
        """
        if self.has_distortion:
            raise InputError("undistort the camera (Camera.undistorted) before transforming it")
        return Camera.from_K(transform.apply_to_K(self.K()), size[1], size[0])

    def resized(self, width: int, height: int) -> Camera:
        """The camera of this image resized (``cv2.resize``) to ``width`` x ``height``.

        A resize scales pixel coordinates only, so a lens model's coefficients (which act on
        normalised coordinates) stay valid and are kept."""
        transform = PixelTransform.resize(self.size, (height, width))
        scaled = Camera.from_K(transform.apply_to_K(self.K()), width, height)
        return Camera(scaled.fx, scaled.fy, scaled.cx, scaled.cy, width, height, self.distortion)

    def rays(self) -> np.ndarray:
        """[H, W, 3] float64: the ray of every pixel centre with z = 1 (camera frame, OpenCV
        axes), no distortion."""
        v, u = np.mgrid[0:self.height, 0:self.width].astype(np.float64)
        return np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], -1)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points [..., 3] (OpenCV axes, Z > 0) -> pixels [..., 2], no distortion."""
        points = np.asarray(points_cam, dtype=np.float64)
        z = points[..., 2]
        return np.stack(
            (self.fx * points[..., 0] / z + self.cx, self.fy * points[..., 1] / z + self.cy),
            axis=-1,
        )

    def projection_matrix(self, near: float, far: float) -> np.ndarray:
        """The OpenGL projection matrix (4x4 float64, row-major, column vectors: ``clip = P @ eye``).

        Convention: ``eye`` is in OpenGL eye coordinates (x right, y **up**, looking down
        **-z**), i.e. ``gl_view_matrix(T_world_cam) @ world``; clip coordinates divide by
        ``w = -z_eye`` into normalised device coordinates in [-1, 1]³ with x right, y up and
        z = -1 at ``near``, +1 at ``far`` (``glFrustum``'s depth mapping). The image's outer
        edges map to NDC ±1: pixel coordinate u = -0.5 (left edge) -> x = -1, u = W - 0.5 ->
        +1; v = -0.5 (top edge) -> y = +1, v = H - 0.5 -> -1. Upload with ``P.T`` to APIs that
        read column-major arrays (``glUniformMatrix4fv(..., GL_FALSE, P.T)``). The same matrix
        as ARCore's ``Camera.getProjectionMatrix`` for equal intrinsics.
        """
        near, far = float(near), float(far)
        if not (0.0 < near < far and math.isfinite(far)):
            raise InputError(f"need 0 < near < far < inf, got near={near}, far={far}")
        w, h = float(self.width), float(self.height)
        projection = np.zeros((4, 4), dtype=np.float64)
        projection[0, 0] = 2.0 * self.fx / w
        projection[0, 2] = 1.0 - 2.0 * (self.cx + 0.5) / w
        projection[1, 1] = 2.0 * self.fy / h
        projection[1, 2] = 2.0 * (self.cy + 0.5) / h - 1.0
        projection[2, 2] = -(far + near) / (far - near)
        projection[2, 3] = -2.0 * far * near / (far - near)
        projection[3, 2] = -1.0
        return projection


def gl_view_matrix(T_world_cam: np.ndarray) -> np.ndarray:
    """OpenGL view matrix (world -> OpenGL eye, 4x4 float64) of a ``T_world_cam`` pose (OpenCV
    axes): ``diag(1, -1, -1, 1) @ inv(T_world_cam)``; pair it with ``Camera.projection_matrix``."""
    pose = np.asarray(T_world_cam, dtype=np.float64)
    if pose.shape != (4, 4):
        raise InputError(f"T_world_cam must be 4x4, got shape {pose.shape}")
    rotation, centre = pose[:3, :3], pose[:3, 3]
    world_to_cam = np.eye(4)
    world_to_cam[:3, :3] = rotation.T
    world_to_cam[:3, 3] = -rotation.T @ centre
    return _CV_TO_GL @ world_to_cam

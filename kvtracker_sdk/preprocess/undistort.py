"""Undistorting frames before the network: OpenCV's remap with maps built once per camera.

Pi3 and Depth Anything 3 model a pinhole camera; a distorted frame (TUM fr1/fr2: k1 0.23-0.26)
bends straight lines the network has learnt to be straight. ``Undistorter`` keeps the image size
and K (``cv2.initUndistortRectifyMap`` with ``newCameraMatrix = K``), so the undistorted frame's
intrinsics are ``camera.undistorted()`` and pixels outside the lens's coverage are black.
Building the maps is the costly part and happens once; each frame then costs one ``cv2.remap``
(figures: ``benchmarks/README.md#figures-behind-the-code``).
OpenCV is imported on first use so that ``import kvtracker_sdk`` stays cheap.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from kvtracker_sdk.errors import InputError
from kvtracker_sdk.geometry.camera import Camera

__all__ = ["Undistorter"]


class Undistorter:
    """Undistorts images of one or more cameras; the remap tables of the last few are cached."""

    def __init__(self, max_cameras: int = 4) -> None:
        self._maps: dict[Camera, tuple[Any, Any]] = {}
        self._max = max(1, int(max_cameras))
        self._lock = threading.Lock()

    def __call__(
        self, image: np.ndarray, camera: Camera, *, nearest: bool = False
    ) -> np.ndarray:
        """``image`` [H, W, C] (any dtype OpenCV remaps) without ``camera``'s distortion.

        Returns ``image`` itself when the camera has none. InputError when the image is not
        the camera's size. ``nearest``: nearest-neighbour sampling (a depth image: blending
        would make depths where nothing is, at edges and beside holes).
        """
        if not camera.has_distortion:
            return image
        if tuple(image.shape[:2]) != camera.size:
            raise InputError(
                f"image {image.shape[0]}x{image.shape[1]} does not match the camera's "
                f"{camera.height}x{camera.width}"
            )
        import cv2

        map_x, map_y = self._maps_for(camera, cv2)
        interpolation = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
        return cv2.remap(image, map_x, map_y, interpolation=interpolation,
                         borderMode=cv2.BORDER_CONSTANT)

    def _maps_for(self, camera: Camera, cv2: Any) -> tuple[Any, Any]:
        with self._lock:
            maps = self._maps.get(camera)
            if maps is None:
                K = camera.K()
                maps = cv2.initUndistortRectifyMap(
                    K, np.asarray(camera.distortion), None, K, (camera.width, camera.height),
                    cv2.CV_16SC2,
                )
                if len(self._maps) >= self._max:
                    self._maps.pop(next(iter(self._maps)))
                self._maps[camera] = maps
            return maps

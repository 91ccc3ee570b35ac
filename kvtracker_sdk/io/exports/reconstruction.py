"""``Reconstruction``: posed images and a point cloud, the common input of the COLMAP and
nerfstudio writers, built from a map's keyframes (and optionally more posed frames).

Why points are re-placed along the camera's rays: COLMAP and nerfstudio model each image as a
pinhole camera, while the network's point map is not constrained to be one (a model with random
or imperfect weights predicts points off the pixel's ray). A fused point is therefore put at the
model's depth z along its pixel's ray under the exported intrinsics, ``X = z K⁻¹ [u, v, 1]``,
then moved to the world by the keyframe's pose: points, cameras and 2D observations agree
exactly, and the depth (the geometry) is the model's. ``pinhole_residual_px`` says how far the
model's own points were from that pinhole (median, pixels).

Frames: world = the tracker's world frame; ``T_world_cam`` camera-to-world, OpenCV axes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.errors import InputError
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.geometry.se3 import project_to_rotation
from kvtracker_sdk.io.exports.export_camera import export_camera

__all__ = ["PosedImage", "Reconstruction", "reconstruction_from_map", "rigid"]


@dataclass(frozen=True)
class PosedImage:
    """One camera: its image (uint8 [H, W, 3] RGB), pose and intrinsics at the image's size."""

    name: str  # file name the writers use, e.g. "kf_0003.png"
    T_world_cam: np.ndarray  # float64 [4, 4]
    image: np.ndarray
    intrinsics: Camera
    timestamp: float | None = None


@dataclass(frozen=True)
class Reconstruction:
    """Images and points; point i was seen by ``images[point_image[i]]`` at ``point_uv[i]``."""

    images: tuple[PosedImage, ...]
    points: np.ndarray  # float64 [M, 3], world frame
    colors: np.ndarray  # uint8 [M, 3]
    point_image: np.ndarray  # int64 [M], index into images
    point_uv: np.ndarray  # float64 [M, 2], pixel centres at integers
    pinhole_residual_px: float = 0.0

    def with_images(self, extra: list[PosedImage]) -> Reconstruction:
        """The same points with ``extra`` images appended (they observe no point)."""
        return Reconstruction(self.images + tuple(extra), self.points, self.colors,
                              self.point_image, self.point_uv, self.pinhole_residual_px)


def reconstruction_from_map(
    keyframe_map: KeyframeMap,
    intrinsics: Camera | None = None,
    *,
    min_confidence: float = 0.5,
    stride: int = 1,
    force_fitted_focal: bool = False,
) -> Reconstruction:
    """The keyframes as posed images (model resolution) and their confident pixels as points.

    ``intrinsics`` are at the map's resolution (``io.export_camera.export_camera`` picks them
    from a map file's stored camera); None: one focal length fitted to every keyframe's local
    points (:func:`estimate_intrinsics`), refused (IntrinsicsError) when under a tenth of the
    image width unless ``force_fitted_focal``. ``stride`` keeps every stride-th pixel in each
    direction (a lighter cloud). Masked keyframes (object mode) contribute only their masked
    pixels.
    """
    if stride < 1:
        raise InputError(f"stride must be >= 1, got {stride}")
    keyframes = keyframe_map.keyframes
    if not keyframes:
        raise InputError("the map has no keyframes")
    if intrinsics is None:
        intrinsics, _origin = export_camera(keyframe_map, min_confidence=min_confidence,
                                            force_fitted_focal=force_fitted_focal)
    rays = intrinsics.rays()
    height, width = rays.shape[:2]
    v, u = np.mgrid[0:height, 0:width]
    sampled = np.zeros((height, width), dtype=bool)
    sampled[::stride, ::stride] = True
    images, points, colors, owners, uvs, residuals = [], [], [], [], [], []
    for index, kf in enumerate(keyframes):
        if kf.image.shape[:2] != (height, width):
            raise InputError(f"keyframe {kf.keyframe_id} is {kf.image.shape[:2]}, the intrinsics "
                             f"are for {(height, width)}")
        pose = rigid(kf.T_world_cam)
        images.append(PosedImage(f"kf_{kf.keyframe_id:04d}.png", pose,
                                 np.ascontiguousarray(kf.image), intrinsics, kf.timestamp))
        depth = kf.local_points[..., 2].astype(np.float64)
        keep = sampled & (kf.confidence_map >= min_confidence) & np.isfinite(depth) & (depth > 0)
        if kf.mask is not None:
            keep &= kf.mask
        camera_points = rays[keep] * depth[keep, None]
        R, t = pose[:3, :3], pose[:3, 3]
        points.append(camera_points @ R.T + t)
        colors.append(kf.image[keep])
        owners.append(np.full(int(keep.sum()), index, dtype=np.int64))
        uvs.append(np.stack([u[keep], v[keep]], axis=1).astype(np.float64))
        residuals.append(_pinhole_residuals(kf.local_points[keep], intrinsics, uvs[-1]))
    all_residuals = np.concatenate(residuals)
    return Reconstruction(
        tuple(images),
        np.concatenate(points),
        np.concatenate(colors).astype(np.uint8),
        np.concatenate(owners),
        np.concatenate(uvs),
        float(np.median(all_residuals)) if all_residuals.size else 0.0,
    )


def rigid(T_world_cam: np.ndarray) -> np.ndarray:
    """The pose with its rotation projected onto SO(3) (a copy).

    Map poses can sit ~1e-6 off a rotation (they went through float32 and Sim(3) gauges);
    formats that store a quaternion make the rotation exact, so the points are placed with the
    same exact rotation, keeping their reprojection exact too.
    """
    pose = np.array(T_world_cam, dtype=np.float64)
    pose[:3, :3] = project_to_rotation(pose[:3, :3])
    return pose


def _pinhole_residuals(
    local_points: np.ndarray, intrinsics: Camera, uv: np.ndarray
) -> np.ndarray:
    """Pixel distance between where the model's points project and the pixels they belong to."""
    if not len(uv):
        return np.zeros(0)
    with np.errstate(divide="ignore", invalid="ignore"):
        projected = intrinsics.project(local_points.astype(np.float64))
    distance = np.linalg.norm(projected - uv, axis=1)
    return distance[np.isfinite(distance)]

"""Write a :class:`Reconstruction` as a COLMAP text model with its images.

Layout (what COLMAP, gaussian-splatting and nerfstudio's ``ns-process-data`` expect)::

    OUT/images/NAME.png                       the images
    OUT/sparse/0/cameras.txt                  PINHOLE fx fy cx cy, one camera per distinct intrinsics
    OUT/sparse/0/images.txt                   QW QX QY QZ TX TY TZ (world-to-camera) + 2D points
    OUT/sparse/0/points3D.txt                 X Y Z R G B ERROR, track (IMAGE_ID, POINT2D_IDX)

Conventions converted here, and only here:
- COLMAP stores ``cam_from_world`` (world-to-camera), quaternion scalar first; the SDK's poses are
  camera-to-world, so the pose is inverted and its rotation written through ``quat_wxyz``.
- COLMAP's pixel coordinates put the *corner* of the image at (0, 0) (the first pixel's centre at
  (0.5, 0.5)); the SDK's put the first pixel's centre at (0, 0). Principal points and 2D points
  are shifted by +0.5.
- Camera axes are OpenCV's in both (x right, y down, z forward): no axis change.
Ids start at 1. ERROR is 0: each point has one observation, on its own ray.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.geometry.se3 import invert_rigid, quat_wxyz_from_rotation
from kvtracker_sdk.io.exports.reconstruction import Reconstruction
from kvtracker_sdk.io.files.atomic import atomic_write

__all__ = ["COLMAP_PIXEL_OFFSET", "write_colmap_text", "write_images"]

COLMAP_PIXEL_OFFSET = 0.5  # COLMAP (and nerfstudio) pixel coordinate = SDK coordinate + 0.5


def write_colmap_text(reconstruction: Reconstruction, out_dir: str | os.PathLike[str]) -> Path:
    """Write the images and ``sparse/0/*.txt`` into ``out_dir``; returns the model folder."""
    out = Path(out_dir)
    model = out / "sparse" / "0"
    model.mkdir(parents=True, exist_ok=True)
    write_images(reconstruction, out / "images")
    camera_ids = _camera_ids(reconstruction)
    _write_cameras(model / "cameras.txt", camera_ids)
    _write_images_txt(model / "images.txt", reconstruction, camera_ids)
    _write_points(model / "points3D.txt", reconstruction)
    return model


def write_images(reconstruction: Reconstruction, folder: Path) -> None:
    """Every image as PNG under ``folder`` (named by ``PosedImage.name``)."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    for posed in reconstruction.images:
        ok, data = cv2.imencode(".png", cv2.cvtColor(posed.image, cv2.COLOR_RGB2BGR))
        if not ok:  # pragma: no cover - OpenCV encodes any uint8 RGB image
            raise RuntimeError(f"PNG encoding failed for {posed.name}")
        with atomic_write(folder / posed.name, binary=True) as handle:
            handle.write(data.tobytes())


def _camera_ids(reconstruction: Reconstruction) -> dict[Camera, int]:
    ids: dict[Camera, int] = {}
    for posed in reconstruction.images:
        ids.setdefault(posed.intrinsics, len(ids) + 1)
    return ids


def _write_cameras(path: Path, camera_ids: dict[Camera, int]) -> None:
    with atomic_write(path) as handle:
        handle.write("# Camera list with one line of data per camera:\n")
        handle.write("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        handle.write(f"# Number of cameras: {len(camera_ids)}\n")
        for camera, camera_id in camera_ids.items():
            cx, cy = camera.cx + COLMAP_PIXEL_OFFSET, camera.cy + COLMAP_PIXEL_OFFSET
            handle.write(f"{camera_id} PINHOLE {camera.width} {camera.height} "
                         f"{camera.fx!r} {camera.fy!r} {cx!r} {cy!r}\n")


def _write_images_txt(
    path: Path, reconstruction: Reconstruction, camera_ids: dict[Camera, int]
) -> None:
    order = np.argsort(reconstruction.point_image, kind="stable")  # points grouped by image
    bounds = np.searchsorted(reconstruction.point_image[order],
                             np.arange(len(reconstruction.images) + 1))
    with atomic_write(path) as handle:
        handle.write("# Image list with two lines of data per image:\n")
        handle.write("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n")
        handle.write("#   POINTS2D[] as (X, Y, POINT3D_ID)\n")
        handle.write(f"# Number of images: {len(reconstruction.images)}\n")
        for index, posed in enumerate(reconstruction.images):
            T_cam_world = invert_rigid(posed.T_world_cam)
            q = quat_wxyz_from_rotation(T_cam_world[:3, :3])
            t = T_cam_world[:3, 3]
            values = " ".join(repr(float(x)) for x in (*q, *t))
            handle.write(f"{index + 1} {values} {camera_ids[posed.intrinsics]} {posed.name}\n")
            mine = order[bounds[index]:bounds[index + 1]]
            uv = reconstruction.point_uv[mine] + COLMAP_PIXEL_OFFSET
            handle.write(" ".join(f"{x!r} {y!r} {pid + 1}"
                                  for (x, y), pid in zip(uv.tolist(), mine.tolist(), strict=True)) + "\n")


def _write_points(path: Path, reconstruction: Reconstruction) -> None:
    # a point's index among its image's 2D points is its rank within the image's group above
    order = np.argsort(reconstruction.point_image, kind="stable")
    rank = np.empty(len(order), dtype=np.int64)
    starts = np.searchsorted(reconstruction.point_image[order], reconstruction.point_image[order])
    rank[order] = np.arange(len(order)) - starts
    with atomic_write(path) as handle:
        handle.write("# 3D point list with one line of data per point:\n")
        handle.write("#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
        handle.write(f"# Number of points: {len(reconstruction.points)}\n")
        rows = zip(reconstruction.points.tolist(), reconstruction.colors.tolist(),
                   reconstruction.point_image.tolist(), rank.tolist(), strict=True)
        for pid, ((x, y, z), (r, g, b), image, index) in enumerate(rows):
            handle.write(f"{pid + 1} {x!r} {y!r} {z!r} {r} {g} {b} 0 {image + 1} {index}\n")

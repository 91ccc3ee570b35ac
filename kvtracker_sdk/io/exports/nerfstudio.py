"""Write a :class:`Reconstruction` as a nerfstudio dataset (``transforms.json``, images, PLY).

    OUT/images/NAME.png
    OUT/transforms.json      intrinsics, one ``transform_matrix`` per frame, ``ply_file_path``
    OUT/points.ply           the points (world frame, colours), for splatting initialisation

Conventions converted here, and only here:
- ``transform_matrix`` is camera-to-world in nerfstudio's (OpenGL/Blender) camera axes: x right,
  y up, z backwards, i.e. ``T_world_cam @ diag(1, -1, -1, 1)``; a camera looks along the third
  column's negative.
- Pixel coordinates put the first pixel's centre at (0.5, 0.5) (as COLMAP): cx, cy + 0.5.
- The world frame is the SDK's (no ``applied_transform``: nothing was reoriented).
Intrinsics are written once at the top when every frame shares them, else per frame.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.io.exports.colmap_text import COLMAP_PIXEL_OFFSET, write_images
from kvtracker_sdk.io.exports.ply import write_ply
from kvtracker_sdk.io.exports.reconstruction import Reconstruction
from kvtracker_sdk.io.files.atomic import atomic_write

__all__ = ["OPENCV_TO_OPENGL", "write_nerfstudio"]

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])  # camera axes: (x, y, z) -> (x, -y, -z)


def write_nerfstudio(reconstruction: Reconstruction, out_dir: str | os.PathLike[str]) -> Path:
    """Write images, ``points.ply`` and ``transforms.json`` into ``out_dir``; returns the JSON."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_images(reconstruction, out / "images")
    write_ply(out / "points.ply", reconstruction.points, reconstruction.colors,
              comment="kvtracker export: world frame")
    shared = {posed.intrinsics for posed in reconstruction.images}
    document: dict[str, Any] = {"camera_model": "OPENCV"}
    if len(shared) == 1:
        document.update(_intrinsics(next(iter(shared))))
    document["frames"] = [
        {
            "file_path": f"images/{posed.name}",
            "transform_matrix": (posed.T_world_cam @ OPENCV_TO_OPENGL).tolist(),
            **({} if len(shared) == 1 else _intrinsics(posed.intrinsics)),
        }
        for posed in reconstruction.images
    ]
    document["ply_file_path"] = "points.ply"
    path = out / "transforms.json"
    with atomic_write(path) as handle:
        json.dump(document, handle, indent=2, allow_nan=False)
        handle.write("\n")
    return path


def _intrinsics(camera: Camera) -> dict[str, Any]:
    return {
        "fl_x": camera.fx, "fl_y": camera.fy,
        "cx": camera.cx + COLMAP_PIXEL_OFFSET, "cy": camera.cy + COLMAP_PIXEL_OFFSET,
        "w": camera.width, "h": camera.height,
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
    }

"""Point clouds as binary PLY files (x, y, z float32; optional red, green, blue uchar; scalars).

Written here rather than with a library: ``plyfile``, the usual numpy PLY package, is GPL-3 and
cannot be a dependency of this BSD-3 SDK (it is a development dependency: the tests read our
files back with it); ``open3d`` and ``trimesh`` would add hundreds of megabytes or a mesh
library for what is a text header followed by one numpy structured array. The format is the
one of Turk's PLY specification, readable by MeshLab, CloudCompare, Open3D and Blender.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from kvtracker_sdk.errors import InputError
from kvtracker_sdk.io.files.atomic import atomic_write

__all__ = ["write_ply"]

_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_RESERVED = {"x", "y", "z", "red", "green", "blue"}


def write_ply(
    path: str | os.PathLike[str],
    points: np.ndarray,
    colors: np.ndarray | None = None,
    *,
    scalars: Mapping[str, np.ndarray] | None = None,
    comment: str | None = None,
) -> Path:
    """Write a binary little-endian PLY point cloud atomically; returns the path.

    ``points``: [N, 3] positions (stored as float32; in the world frame of the trajectory they
    belong to). ``colors``: [N, 3] RGB, uint8 or floats in [0, 1]. ``scalars``: extra per-point
    float32 properties by name, e.g. ``{"confidence": conf}`` with ``conf`` of shape [N].
    ``comment``: one line stored in the header. N may be 0.
    """
    xyz = _points(points)
    fields: list[tuple[str, np.ndarray, str, str]] = [
        (axis, xyz[:, k], "<f4", "float") for k, axis in enumerate("xyz")
    ]
    if colors is not None:
        rgb = _colors(colors, len(xyz))
        fields += [
            (name, rgb[:, k], "u1", "uchar") for k, name in enumerate(("red", "green", "blue"))
        ]
    for name, values in (scalars or {}).items():
        fields.append((name, _scalar(name, values, len(xyz)), "<f4", "float"))

    vertices = np.empty(len(xyz), dtype=[(name, dtype) for name, _, dtype, _ in fields])
    for name, values, _, _ in fields:
        vertices[name] = values
    header = ["ply", "format binary_little_endian 1.0"]
    if comment:
        # one ASCII line: the header is ASCII and a newline would end the comment early
        header.append("comment " + " ".join(comment.split()).encode("ascii", "replace").decode())
    header.append(f"element vertex {len(xyz)}")
    header += [f"property {ply_type} {name}" for name, _, _, ply_type in fields]
    header.append("end_header")

    target = Path(path)
    with atomic_write(target, binary=True) as handle:
        handle.write(("\n".join(header) + "\n").encode("ascii"))
        handle.write(vertices.tobytes())
    return target


def _points(points: np.ndarray) -> np.ndarray:
    xyz = np.asarray(points)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or not np.issubdtype(xyz.dtype, np.number):
        raise InputError(f"points must be a numeric [N, 3] array, got {xyz.dtype} {xyz.shape}")
    xyz = xyz.astype(np.float32)
    if not np.all(np.isfinite(xyz)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(xyz), axis=1)))
        raise InputError(
            f"{bad} points are NaN, infinite or beyond float32 range; filter them first"
        )
    return xyz


def _colors(colors: np.ndarray, count: int) -> np.ndarray:
    rgb = np.asarray(colors)
    if rgb.shape != (count, 3):
        raise InputError(f"colors must have shape [{count}, 3] like the points, got {rgb.shape}")
    if rgb.dtype == np.uint8:
        return rgb
    if not np.issubdtype(rgb.dtype, np.floating):
        raise InputError(f"colors must be uint8 or floats in [0, 1], got {rgb.dtype}")
    if not (
        np.all(np.isfinite(rgb)) and rgb.min(initial=0.0) >= 0.0 and rgb.max(initial=0.0) <= 1.0
    ):
        raise InputError("float colors must lie in [0, 1]")
    return np.round(rgb * 255.0).astype(np.uint8)


def _scalar(name: str, values: np.ndarray, count: int) -> np.ndarray:
    if not _NAME.match(name) or name in _RESERVED:
        raise InputError(
            f"scalar property name {name!r} must be an identifier other than x y z red green blue"
        )
    array = np.asarray(values)
    if array.shape != (count,) or not np.issubdtype(array.dtype, np.number):
        raise InputError(
            f"scalar {name!r} must be a numeric [{count}] array, got {array.dtype} {array.shape}"
        )
    return array.astype(np.float32)

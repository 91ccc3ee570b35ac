"""Exports of a map for other tools: its fused point cloud (PLY) and keyframe trajectory (TUM).

Both read only the map's keyframes (world frame), so they work on a live tracker's map and on a
map loaded from a file alike, and both write atomically.
"""

from __future__ import annotations

import os

import numpy as np

from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.errors import InputError
from kvtracker_sdk.io.exports.ply import write_ply
from kvtracker_sdk.io.files.trajectory import Trajectory, write_tum

__all__ = ["export_keyframe_trajectory", "export_point_cloud", "fused_point_cloud"]


def fused_point_cloud(
    keyframe_map: KeyframeMap,
    *,
    min_confidence: float = 0.5,
    use_masks: bool = True,
    voxel_size: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points of every keyframe pixel with confidence >= ``min_confidence``.

    Returns ``points`` [M, 3] float64 (world frame), ``colors`` [M, 3] uint8 (the keyframe
    image's RGB) and ``confidence`` [M] float32. With ``use_masks``, keyframes that have an object
    mask contribute only masked pixels. ``voxel_size`` (world units) keeps the most confident
    point of each occupied voxel, removing the duplicates that overlapping keyframes produce.
    """
    if not 0.0 <= min_confidence <= 1.0:
        raise InputError(f"min_confidence must lie in [0, 1], got {min_confidence}")
    if voxel_size is not None and not (np.isfinite(voxel_size) and voxel_size > 0):
        raise InputError(f"voxel_size must be a finite number > 0, got {voxel_size}")
    points, colors, confidence = [], [], []
    for kf in keyframe_map.keyframes:
        keep = kf.confidence_map >= min_confidence
        if use_masks and kf.mask is not None:
            keep &= kf.mask
        with np.errstate(invalid="ignore"):  # a model may emit inf depth (sky): dropped below
            world = kf.world_points()[keep]
        finite = np.all(np.isfinite(world), axis=1)
        points.append(world[finite])
        colors.append(kf.image[keep][finite])
        confidence.append(kf.confidence_map[keep][finite])
    xyz = np.concatenate(points) if points else np.zeros((0, 3))
    rgb = np.concatenate(colors) if colors else np.zeros((0, 3), np.uint8)
    conf = np.concatenate(confidence) if confidence else np.zeros(0, np.float32)
    if voxel_size is not None and len(xyz):
        order = np.argsort(-conf, kind="stable")  # most confident first: np.unique keeps firsts
        voxels = np.floor(xyz[order] / voxel_size).astype(np.int64)
        _, first = np.unique(voxels, axis=0, return_index=True)
        selected = order[np.sort(first)]
        xyz, rgb, conf = xyz[selected], rgb[selected], conf[selected]
    return xyz, rgb, conf


def export_point_cloud(
    keyframe_map: KeyframeMap,
    path: str | os.PathLike[str],
    *,
    min_confidence: float = 0.5,
    use_masks: bool = True,
    voxel_size: float | None = None,
) -> int:
    """Write the map's fused, confidence-filtered point cloud as binary PLY; returns the point count.

    Points are in the map's world frame with the keyframe images' colours and a ``confidence``
    scalar per point; see :func:`fused_point_cloud` for the filters.
    """
    points, colors, confidence = fused_point_cloud(
        keyframe_map, min_confidence=min_confidence, use_masks=use_masks, voxel_size=voxel_size
    )
    write_ply(
        path,
        points,
        colors,
        scalars={"confidence": confidence},
        comment=f"kvtracker map: {keyframe_map.num_keyframes} keyframes, world frame",
    )
    return len(points)


def export_keyframe_trajectory(keyframe_map: KeyframeMap, path: str | os.PathLike[str]) -> int:
    """Write the keyframes' ``T_world_cam`` as a TUM trajectory; returns the number of poses.

    Rows (``timestamp tx ty tz qx qy qz qw``, world frame) are sorted by time. TUM needs a
    number in the first column: if any keyframe lacks a timestamp, every keyframe is stamped
    with its frame index instead, so that seconds and indices never mix.
    """
    keyframes = keyframe_map.keyframes
    if any(kf.timestamp is None for kf in keyframes):
        stamps = np.array([float(kf.frame_index) for kf in keyframes])
    else:
        stamps = np.array([kf.timestamp for kf in keyframes], dtype=np.float64)
    order = np.argsort(stamps, kind="stable")
    trajectory = Trajectory(stamps[order], keyframe_map.poses()[order])
    write_tum(path, trajectory)
    return len(trajectory)

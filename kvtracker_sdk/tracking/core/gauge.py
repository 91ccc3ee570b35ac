"""World-frame continuity: the Sim(3) that maps each mapping pass's raw frame into the world frame.

Every pass of a multi-view transformer returns poses in its own frame and scale. The first map
fixes the world: keyframe 0 is the identity and the first pass's scale is the world's. Each later
pass is aligned to the previous map through the keyframes both share (design doc):

* scale from their depths: the median over pixels of (world depth / raw depth), where the world
  depth is the previous map's local point z (world scale) and the raw depth the new pass's; one
  shared keyframe has thousands of pixels, so one suffices;
* rotation from their poses: the chordal mean of ``R_world_i @ R_raw_i^T`` (an SVD projection of
  the sum);
* translation from their camera centres once scale and rotation are known: the mean of
  ``c_world_i - s R c_raw_i``.

Poses alone could not give the scale with one shared keyframe (a camera centre has no extent);
depths give it from a single view, which is what makes a rebuild after heavy eviction safe.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from kvtracker_sdk.cache.keyframe_map import Keyframe
from kvtracker_sdk.geometry.se3 import invert_rigid, project_to_rotation, rotation_angle_deg
from kvtracker_sdk.geometry.sim3 import Sim3

__all__ = ["Correction", "anchor_gauge", "depth_scale", "estimate_gauge", "keyframe_corrections"]


def anchor_gauge(raw_pose_keyframe0: np.ndarray, scale: float = 1.0) -> Sim3:
    """First map: the transform putting keyframe 0 at the identity. ``scale`` 1: the first pass's
    scale becomes the world's; a metric scale (metres per raw unit, from sensor depth) makes the
    world metric from its first map on."""
    T_cam_raw = invert_rigid(raw_pose_keyframe0)
    return Sim3(T_cam_raw[:3, :3], scale * T_cam_raw[:3, 3], scale)


def depth_scale(
    world_points: Sequence[np.ndarray],
    raw_points: Sequence[np.ndarray],
    masks: Sequence[np.ndarray | None],
    *,
    stride: int = 4,
) -> float:
    """Median of world depth / raw depth over the pixels of the shared keyframes.

    ``world_points`` / ``raw_points``: per keyframe [H, W, 3] camera-frame points (z = depth) in
    world and raw scale; ``masks``: bool [H, W] or None. Pixels with non-positive or non-finite
    depth on either side are ignored. Returns 1.0 if no pixel is usable.
    """
    ratios = []
    for world, raw, mask in zip(world_points, raw_points, masks, strict=True):
        z_world = np.asarray(world[::stride, ::stride, 2], dtype=np.float64)
        z_raw = np.asarray(raw[::stride, ::stride, 2], dtype=np.float64)
        valid = np.isfinite(z_world) & np.isfinite(z_raw) & (z_world > 0) & (z_raw > 0)
        if mask is not None:
            valid &= mask[::stride, ::stride]
        ratios.append(z_world[valid] / z_raw[valid])
    samples = np.concatenate(ratios) if ratios else np.empty(0)
    return float(np.median(samples)) if samples.size else 1.0


def estimate_gauge(
    world_poses: np.ndarray,
    raw_poses: np.ndarray,
    scale: float,
) -> Sim3:
    """The Sim(3) with ``world ≈ S(raw)`` for shared keyframes, given the depth-derived ``scale``.

    ``world_poses`` and ``raw_poses`` are [K, 4, 4] T_world_cam of the same K >= 1 keyframes in the
    world frame and in the new pass's raw frame.
    """
    world = np.asarray(world_poses, dtype=np.float64).reshape(-1, 4, 4)
    raw = np.asarray(raw_poses, dtype=np.float64).reshape(-1, 4, 4)
    rotation = project_to_rotation(
        np.einsum("kij,klj->il", world[:, :3, :3], raw[:, :3, :3])  # sum_k R_world_k R_raw_k^T
    )
    translation = np.mean(world[:, :3, 3] - scale * raw[:, :3, 3] @ rotation.T, axis=0)
    return Sim3(rotation, translation, scale)


@dataclass(frozen=True)
class Correction:
    """How a rebuild moved the shared keyframes in the world frame."""

    transforms: Mapping[int, np.ndarray]  # id -> C with T_new = C @ T_old (rigid [4, 4])
    max_translation: float  # largest camera-centre displacement, world units
    max_rotation_deg: float  # largest change of orientation


def keyframe_corrections(old: Sequence[Keyframe], new: Sequence[Keyframe]) -> Correction:
    """Corrections of the keyframes present in both ``old`` and ``new`` (matched by id)."""
    new_by_id = {kf.keyframe_id: kf for kf in new}
    transforms: dict[int, np.ndarray] = {}
    max_translation = 0.0
    max_rotation = 0.0
    for kf in old:
        updated = new_by_id.get(kf.keyframe_id)
        if updated is None:
            continue
        transforms[kf.keyframe_id] = updated.T_world_cam @ invert_rigid(kf.T_world_cam)
        shift = float(np.linalg.norm(updated.T_world_cam[:3, 3] - kf.T_world_cam[:3, 3]))
        turn = rotation_angle_deg(kf.T_world_cam[:3, :3], updated.T_world_cam[:3, :3])
        max_translation = max(max_translation, shift)
        max_rotation = max(max_rotation, turn)
    return Correction(transforms, max_translation, max_rotation)

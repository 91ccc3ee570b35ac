"""Keyframe policies: when a tracked frame becomes a keyframe, and which keyframe leaves a full map.

* Scene mode (KV-Tracker paper): a keyframe every ``interval_frames`` frames.
* Object mode, ``view_direction`` rule (the default): a new keyframe when the angle between the
  unit directions from the object centre to the camera and to *every* keyframe exceeds
  ``view_angle_deg`` — a cone of τ around each keyframe's view, the same on any ring and near the
  poles.
* Object mode, ``azimuth_elevation`` rule (KV-Tracker paper as written): the view direction as
  azimuth/elevation in the world frame; a new keyframe when min |Δazimuth| or min |Δelevation|
  over all keyframes exceeds ``view_angle_deg``, each axis judged alone (so a ring 30° above a
  full ring adds nothing, and an orbit near the pole adds one per τ of azimuth).
* Budget (design doc): at most ``max_keyframes`` keyframes and ``max_cache_bytes`` of K/V; when a
  new keyframe would exceed it, evict by policy — never keyframe 0, the anchor of the world frame.

World frame convention (the tracker's): keyframe 0 of the first map is the identity, OpenCV axes,
so "up" is -y of keyframe 0's camera. Azimuth is measured around that up axis (0° = looking along
keyframe 0's +z), elevation above the x-z plane.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from kvtracker_sdk.cache.keyframe_map import Keyframe
from kvtracker_sdk.config import BudgetConfig, EvictionPolicy, ObjectKeyframeRule
from kvtracker_sdk.tracking.object.object_model import POINT_STEP, fused_object_points

__all__ = [
    "KeyframeBudget",
    "angle_difference_deg",
    "interval_elapsed",
    "novel_object_view",
    "novel_view",
    "novel_view_direction",
    "object_centre",
    "view_direction",
    "view_angles_deg",
]


def interval_elapsed(frame_index: int, last_keyframe_frame: int, interval_frames: int) -> bool:
    """Scene rule: at least ``interval_frames`` frames since the last keyframe's frame."""
    return frame_index - last_keyframe_frame >= interval_frames


def object_centre(keyframes: Sequence[Keyframe], *, step: int = POINT_STEP) -> np.ndarray:
    """Mean world point [3] of the fused object points (``object_model.fused_object_points``:
    masked, confident, foreground pixels of every ``step``-th row and column of all keyframes);
    the mean of all masked points (all pixels where unmasked) if none is left."""
    fused = fused_object_points(keyframes, step=step)
    if len(fused):
        return fused.mean(axis=0)
    chunks = []
    for kf in keyframes:
        points = kf.world_points()
        selected = points[kf.mask] if kf.mask is not None else points.reshape(-1, 3)
        chunks.append(selected[::step])
    points = np.concatenate(chunks)
    return points[np.all(np.isfinite(points), axis=1)].mean(axis=0)


def view_angles_deg(T_world_cam: np.ndarray, centre: np.ndarray) -> tuple[float, float]:
    """(azimuth, elevation) in degrees of the direction from ``centre`` to the camera centre.

    World frame with OpenCV axes: up is -y. azimuth = atan2(x, z) in [-180, 180),
    elevation = atan2(-y, hypot(x, z)) in [-90, 90].
    """
    d = np.asarray(T_world_cam, dtype=np.float64)[:3, 3] - np.asarray(centre, dtype=np.float64)
    azimuth = np.degrees(np.arctan2(d[0], d[2]))
    elevation = np.degrees(np.arctan2(-d[1], np.hypot(d[0], d[2])))
    return float(azimuth), float(elevation)


def angle_difference_deg(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    """|a - b| wrapped to [0, 180] (so 179° and -179° are 2° apart)."""
    diff = (np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64) + 180.0) % 360.0
    return np.abs(diff - 180.0)


def view_direction(T_world_cam: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Unit vector [3] from ``centre`` to the camera centre (world frame; [0, 0, 0] if equal)."""
    d = np.asarray(T_world_cam, dtype=np.float64)[..., :3, 3] - np.asarray(centre, dtype=np.float64)
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    return np.where(norm > 0, d / np.where(norm > 0, norm, 1.0), 0.0)


def novel_view_direction(
    T_world_cam: np.ndarray,
    keyframe_poses: np.ndarray,
    centre: np.ndarray,
    threshold_deg: float,
) -> bool:
    """View-direction rule: the angle between the unit directions from ``centre`` to the camera
    and to every keyframe (``keyframe_poses`` [N, 4, 4] T_world_cam, N >= 1) exceeds the
    threshold."""
    current = view_direction(T_world_cam, centre)
    others = view_direction(np.asarray(keyframe_poses, dtype=np.float64), centre)  # [N, 3]
    best_cos = float(np.clip(others @ current, -1.0, 1.0).max())
    return best_cos < float(np.cos(np.radians(threshold_deg)))


def novel_object_view(
    rule: ObjectKeyframeRule,
    T_world_cam: np.ndarray,
    keyframe_poses: np.ndarray,
    centre: np.ndarray,
    threshold_deg: float,
) -> bool:
    """Whether the object keyframe ``rule`` wants a keyframe at ``T_world_cam``."""
    if rule is ObjectKeyframeRule.VIEW_DIRECTION:
        return novel_view_direction(T_world_cam, keyframe_poses, centre, threshold_deg)
    return novel_view(T_world_cam, keyframe_poses, centre, threshold_deg)


def novel_view(
    T_world_cam: np.ndarray,
    keyframe_poses: np.ndarray,
    centre: np.ndarray,
    threshold_deg: float,
) -> bool:
    """Paper's object rule: min |Δazimuth| or min |Δelevation| over keyframes exceeds the threshold.

    ``keyframe_poses`` is [N, 4, 4] T_world_cam (N >= 1).
    """
    azimuth, elevation = view_angles_deg(T_world_cam, centre)
    d = np.asarray(keyframe_poses, dtype=np.float64)[:, :3, 3] - np.asarray(centre, dtype=np.float64)
    azimuths = np.degrees(np.arctan2(d[:, 0], d[:, 2]))  # as view_angles_deg, for all at once
    elevations = np.degrees(np.arctan2(-d[:, 1], np.hypot(d[:, 0], d[:, 2])))
    min_d_azimuth = float(angle_difference_deg(azimuth, azimuths).min())
    min_d_elevation = float(angle_difference_deg(elevation, elevations).min())
    return min_d_azimuth > threshold_deg or min_d_elevation > threshold_deg


class KeyframeBudget:
    """The map's size limit and its eviction rule (keyframe 0 is never evicted)."""

    def __init__(self, config: BudgetConfig) -> None:
        self.config = config

    def capacity(self, bytes_per_keyframe: int) -> int | None:
        """Max keyframes allowed by count and bytes (>= 1: keyframe 0 always fits); None: no limit."""
        limits = []
        if self.config.max_keyframes is not None:
            limits.append(self.config.max_keyframes)
        if self.config.max_cache_bytes is not None and bytes_per_keyframe > 0:
            limits.append(self.config.max_cache_bytes // bytes_per_keyframe)
        return max(1, min(limits)) if limits else None

    def select_evictions(
        self, keyframes: Sequence[Keyframe], bytes_per_keyframe: int, *, adding: int = 1
    ) -> tuple[int, ...]:
        """Ids to drop so that ``keyframes`` plus ``adding`` new ones fit the budget.

        ``keyframes[0]`` is keyframe 0 and is never selected. If even keyframe 0 alone plus the new
        keyframes do not fit, every other keyframe is selected (the caller should not add).
        """
        capacity = self.capacity(bytes_per_keyframe)
        excess = 0 if capacity is None else len(keyframes) + adding - capacity
        if excess <= 0:
            return ()
        candidates = list(keyframes[1:])
        if excess >= len(candidates):
            return tuple(kf.keyframe_id for kf in candidates)
        if self.config.eviction is EvictionPolicy.OLDEST:
            # by keyframe id, which never goes back: frame indices restart in every session (a
            # loaded map's keyframes have indices of an earlier session), ids do not
            order = sorted(candidates, key=lambda kf: kf.keyframe_id)
            return tuple(kf.keyframe_id for kf in order[:excess])
        return _most_redundant(list(keyframes), excess)


def _pose_distances(keyframes: Sequence[Keyframe]) -> np.ndarray:
    """[N, N] pose distance: centre distance over the median scene depth plus rotation in radians.

    Dividing by the scene depth makes translation unit-free (a monocular map has no metric scale),
    so 1 ≈ moving by the viewing distance ≈ turning by 57°.
    """
    poses = np.stack([kf.T_world_cam for kf in keyframes])
    centres = poses[:, :3, 3]
    depths = np.concatenate([kf.local_points[::8, ::8, 2].ravel() for kf in keyframes])
    depths = depths[np.isfinite(depths) & (depths > 0)]
    scale = float(np.median(depths)) if depths.size else 1.0
    translation = np.linalg.norm(centres[:, None] - centres[None], axis=-1) / max(scale, 1e-9)
    relative = np.einsum("aji,bjk->abik", poses[:, :3, :3], poses[:, :3, :3])  # R_a^T R_b
    cos = np.clip((np.trace(relative, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return translation + np.arccos(cos)


def _most_redundant(keyframes: list[Keyframe], excess: int) -> tuple[int, ...]:
    """Greedily drop the non-anchor keyframe closest to any other remaining keyframe."""
    distances = _pose_distances(keyframes)
    np.fill_diagonal(distances, np.inf)
    alive = list(range(len(keyframes)))
    evicted: list[int] = []
    for _ in range(excess):
        sub = distances[np.ix_(alive, alive)]
        nearest = sub.min(axis=1)
        nearest[0] = np.inf  # alive[0] is keyframe 0: never evicted
        victim = alive[int(np.argmin(nearest))]
        evicted.append(keyframes[victim].keyframe_id)
        alive.remove(victim)
    return tuple(evicted)

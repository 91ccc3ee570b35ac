"""Keyframe policies: when a tracked frame becomes a keyframe, and which keyframe leaves a full map.

* Scene mode (KV-Tracker paper): a keyframe every ``interval_frames`` frames.
* Object mode (KV-Tracker paper): the view direction from the object centre to the camera, as
  azimuth/elevation in the world frame; a new keyframe when min |Δazimuth| or min |Δelevation|
  over all keyframes exceeds ``view_angle_deg``.
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
from kvtracker_sdk.config import BudgetConfig, EvictionPolicy

__all__ = [
    "KeyframeBudget",
    "angle_difference_deg",
    "interval_elapsed",
    "novel_view",
    "object_centre",
    "view_angles_deg",
]


def interval_elapsed(frame_index: int, last_keyframe_frame: int, interval_frames: int) -> bool:
    """Scene rule: at least ``interval_frames`` frames since the last keyframe's frame."""
    return frame_index - last_keyframe_frame >= interval_frames


def object_centre(keyframes: Sequence[Keyframe], *, step: int = 4) -> np.ndarray:
    """Mean world point [3] of the masked pixels of all keyframes (all pixels where unmasked).

    ``step`` keeps every step-th selected point (the mean of a dense point map barely changes).
    Input validation guarantees non-empty masks, so some point always exists.
    """
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


def novel_view(
    T_world_cam: np.ndarray,
    keyframe_poses: np.ndarray,
    centre: np.ndarray,
    threshold_deg: float,
) -> bool:
    """Object rule: min |Δazimuth| or min |Δelevation| over keyframes exceeds the threshold.

    ``keyframe_poses`` is [N, 4, 4] T_world_cam (N >= 1).
    """
    azimuth, elevation = view_angles_deg(T_world_cam, centre)
    angles = np.array([view_angles_deg(T, centre) for T in keyframe_poses])  # [N, 2]
    min_d_azimuth = float(angle_difference_deg(azimuth, angles[:, 0]).min())
    min_d_elevation = float(angle_difference_deg(elevation, angles[:, 1]).min())
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

"""The object as the map knows it: fused object points, its centre, its frame and its extent.

**Fused object points**: the world points (the backend's local points through each keyframe's
``T_world_cam``) of every keyframe's masked pixels that are confident and in the mask's
**foreground**. The foreground rule exists because a box (or a loose mask) also covers background:
the wall behind a mug would otherwise become part of the "object" and its projection would swell
the predicted region with every keyframe. Per keyframe:

* ``d_c``: the median depth of the masked pixels in the middle half of the mask's box (where the
  object is, whatever the box's corners show);
* ``L``: the mask's lateral extent at that depth, ``d_c`` times the larger spread of the rays'
  slopes X/Z, Y/Z over the mask (no intrinsics needed: the local points carry their rays);
* kept: masked pixels with depth in ``[d_c - L, d_c + L]`` (an object is assumed no deeper than
  it is wide as seen; the far background of a box is dropped, a desk top at the object's depth is
  not — a real mask from a ``Segmenter`` avoids that).

The **anchor ball** bounds what later keyframes may add: the first keyframe (keyframe 0, the frame
the app pointed at the object) gives the object's centre c0 and radius r0 (98th percentile of its
points' distances to c0), and fused points must lie within 2 r0 of c0. Later keyframes' masks are
*predicted* regions grown a little (so that newly seen surface enters the map); without the ball,
a background at the object's depth (the desk under a mug) could enter with each keyframe and the
region would grow without end. The far side of a round object lies within 1.5 r0 of c0; an object
much longer than it first looked (a pen seen end-on) is cut at 2 r0.

**Object frame** (``ObjectFrame``): origin at the object centre (the mean of the fused points, the
centre the object keyframe rule turns around), axes of keyframe 0's camera. **Extent**: an
``OrientedBox`` of the fused points along their principal axes, in object coordinates.

Everything is recomputed when the map object changes (every accepted rebuild moves all keyframes
a little) and reused otherwise; the keyframes are sampled more sparsely as the map grows
(``sampling_step``), ~25 ms per rebuild for 35 keyframes at 196x252 on one core.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from kvtracker_sdk.cache.keyframe_map import Keyframe, KeyframeMap
from kvtracker_sdk.geometry.boxes import OrientedBox
from kvtracker_sdk.types import ObjectFrame

__all__ = [
    "MAX_MODEL_POINTS",
    "POINT_STEP",
    "ObjectModel",
    "ObjectModelCache",
    "foreground_points",
    "fused_object_points",
    "sampling_step",
    "voxel_subsample",
]

POINT_STEP = 2  # every 2nd row and column of a keyframe: dense enough to fill a silhouette
MAX_MODEL_POINTS = 4096  # points projected twice per frame (~1 ms per frame at 196x252)
_MIN_CONFIDENCE_RATIO = 0.5  # of the keyframe's median masked confidence (drops flying pixels)
_FUSED_POINTS = 16384  # fused points sampled per map (the model keeps MAX_MODEL_POINTS of them)
_ANCHOR_RADII = 2.0  # fused points lie within this many radii of the first keyframe's object


def foreground_points(keyframe: Keyframe, *, step: int = POINT_STEP) -> np.ndarray:
    """World points [N, 3] of ``keyframe``'s masked, confident, foreground pixels (every
    ``step``-th row and column); all pixels count as masked without a mask. See the module
    docstring for the foreground rule."""
    local = keyframe.local_points[::step, ::step].astype(np.float64)
    confidence = keyframe.confidence_map[::step, ::step]
    selected = (
        np.ones(local.shape[:2], dtype=bool) if keyframe.mask is None
        else keyframe.mask[::step, ::step].copy()
    )  # fmt: skip
    selected &= np.isfinite(local).all(axis=-1) & (local[..., 2] > 0)
    if not selected.any():
        return np.empty((0, 3))
    selected &= confidence >= _MIN_CONFIDENCE_RATIO * float(np.median(confidence[selected]))
    rows, cols = np.nonzero(selected)
    if rows.size == 0:
        return np.empty((0, 3))
    depth = local[rows, cols, 2]
    centre_r, centre_c = (rows.min() + rows.max()) / 2.0, (cols.min() + cols.max()) / 2.0
    middle = (np.abs(rows - centre_r) <= (rows.max() - rows.min()) / 4.0) & (
        np.abs(cols - centre_c) <= (cols.max() - cols.min()) / 4.0
    )
    d_c = float(np.median(depth[middle] if middle.any() else depth))
    slope_x, slope_y = local[rows, cols, 0] / depth, local[rows, cols, 1] / depth
    lateral = d_c * max(float(np.ptp(slope_x)), float(np.ptp(slope_y)))
    keep = np.abs(depth - d_c) <= max(lateral, 1e-9)
    points = local[rows[keep], cols[keep]]
    R, t = keyframe.T_world_cam[:3, :3], keyframe.T_world_cam[:3, 3]
    return points @ R.T + t


def fused_object_points(keyframes: Sequence[Keyframe], *, step: int = POINT_STEP) -> np.ndarray:
    """All keyframes' ``foreground_points`` [N, 3] in the world frame (N may be 0), within the
    anchor ball of the first keyframe's (see the module docstring)."""
    chunks = [foreground_points(kf, step=step) for kf in keyframes]
    if not chunks or len(chunks[0]) == 0:
        return np.concatenate(chunks) if chunks else np.empty((0, 3))
    anchor = chunks[0]
    centre = anchor.mean(axis=0)
    radius = float(np.quantile(np.linalg.norm(anchor - centre, axis=1), 0.98))
    points = np.concatenate(chunks)
    inside = np.linalg.norm(points - centre, axis=1) <= _ANCHOR_RADII * max(radius, 1e-12)
    return points[inside]


def voxel_subsample(points: np.ndarray, limit: int) -> np.ndarray:
    """At most ``limit`` of ``points`` [N, 3], one per cell of the finest cubic grid that leaves
    no more (cells grow by 1.5x from 1/32 of the largest extent). Uniform in space, not over the
    pixels the points came from: a silhouette's rim, seen at a grazing angle by the keyframes, has
    few pixel samples and must keep them (an even subsample of the samples thins it out, and the
    predicted box shrinks on that side)."""
    if len(points) <= limit:
        return points.copy()
    low = points.min(axis=0)
    cell = max(float(np.ptp(points, axis=0).max()) / 32.0, 1e-12)
    while True:
        cells = np.floor((points - low) / cell).astype(np.int64)  # [N, 3], each < 2**20
        keys = (cells[:, 0] << 40) | (cells[:, 1] << 20) | cells[:, 2]
        _, first = np.unique(keys, return_index=True)
        if len(first) <= limit:
            return points[np.sort(first)]
        cell *= 1.5


def sampling_step(keyframes: Sequence[Keyframe]) -> int:
    """Every how many rows and columns the keyframes' masked pixels are sampled: about
    ``_FUSED_POINTS`` samples in all (a few keyframes: every 2nd pixel; dozens: every 4th or
    more), so that recomputing the object after a rebuild stays cheap as the map grows."""
    masked = sum(int(kf.mask.sum()) if kf.mask is not None else kf.confidence_map.size
                 for kf in keyframes)
    return int(min(8, max(POINT_STEP, math.ceil(math.sqrt(masked / _FUSED_POINTS)))))


@dataclass(frozen=True)
class ObjectModel:
    """One map's object: ``points`` [N <= MAX_MODEL_POINTS, 3] (world, evenly subsampled fused
    points, for projection), ``centre`` [3] (mean of all fused points) and ``frame``."""

    points: np.ndarray
    centre: np.ndarray
    frame: ObjectFrame

    @classmethod
    def of(cls, kf_map: KeyframeMap) -> ObjectModel | None:
        """The object of ``kf_map``; None when no keyframe has a usable foreground point."""
        fused = fused_object_points(kf_map.keyframes, step=sampling_step(kf_map.keyframes))
        if len(fused) == 0:
            return None
        centre = fused.mean(axis=0)
        T_world_object = np.eye(4)
        T_world_object[:3, :3] = kf_map.keyframes[0].T_world_cam[:3, :3]
        T_world_object[:3, 3] = centre
        T_object_world = np.linalg.inv(T_world_object)
        local = fused @ T_object_world[:3, :3].T + T_object_world[:3, 3]
        extent = OrientedBox.fit(local)
        points = voxel_subsample(fused, MAX_MODEL_POINTS)
        points.setflags(write=False)
        frame = ObjectFrame(T_world_object, extent, int(len(local)), kf_map.generation)
        return cls(points, centre, frame)


class ObjectModelCache:
    """The ``ObjectModel`` of the latest map seen, recomputed only when the map object changes."""

    def __init__(self) -> None:
        self._map: KeyframeMap | None = None  # held, so that its id is not reused
        self._model: ObjectModel | None = None

    def get(self, kf_map: KeyframeMap | None) -> ObjectModel | None:
        if kf_map is None:
            return None
        if kf_map is not self._map:
            self._map, self._model = kf_map, ObjectModel.of(kf_map)
        return self._model

    def clear(self) -> None:
        self._map = self._model = None

"""The object as the map knows it: fused object points, its centre, its frame and its extent.

**Fused object points**: the world points (the backend's local points through each keyframe's
``T_world_cam``) of every keyframe's masked pixels that are confident and in the mask's
**foreground**, then separated from what the object stands on and what stands beside it
(``object_separation``). The foreground rule exists because a box (or a loose mask) also covers
background: the wall behind a mug would otherwise become part of the "object" and its projection
would swell the predicted region with every keyframe. Per keyframe:

* ``d_c``: the median depth of the masked pixels in the middle half of the mask's box (where the
  object is, whatever the box's corners show);
* ``L``: the mask's lateral extent at that depth, ``d_c`` times the larger spread of the rays'
  slopes X/Z, Y/Z over the mask (no intrinsics needed: the local points carry their rays);
* kept: masked pixels with depth in ``[d_c - L, d_c + L]`` (an object is assumed no deeper than
  it is wide as seen; the far background of a box is dropped, a desk top at the object's depth is
  not: the separation's support planes are).

Then, from all keyframes at once: points on or behind the **support planes** found around
keyframe 0's box are dropped (per keyframe), and of what is left only the **3D connected
component** holding most of keyframe 0's points is kept (the neighbour beside the object is
another component). Never is a keyframe's mask, grown from the previous prediction, trusted
without these filters: the desk it also covers would enter with every keyframe.

The **anchor ball** still bounds what later keyframes may add: keyframe 0's separated points
give the object's centre c0 and radius r0 (98th percentile of their distances to c0), and fused
points must lie within 2 r0 of c0. The far side of a round object lies within 1.5 r0 of c0; an
object much longer than it first looked (a pen seen end-on) is cut at 2 r0.

**Object frame** (``ObjectFrame``): for an object standing on a support plane, z along the
plane's normal (``up``), x keyframe 0's camera x laid onto the plane, origin at the centre of the
extent, which is the smallest footprint rectangle from the plane to the top (``_standing_frame``);
for a floating object, origin at the mean of the fused points and axes of keyframe 0's camera,
extent along the points' principal axes. ``ObjectModel.centre`` (the origin) is the centre the
object keyframe rule turns around.

Everything is recomputed when the map object changes (every accepted rebuild moves all keyframes
a little) and reused otherwise; the keyframes are sampled more sparsely as the map grows
(``sampling_step``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from kvtracker_sdk.cache.keyframe_map import Keyframe, KeyframeMap
from kvtracker_sdk.geometry.boxes import OrientedBox
from kvtracker_sdk.tracking.object.object_separation import (
    Plane3,
    SupportPlanes,
    drop_behind,
    find_planes,
    object_component,
)
from kvtracker_sdk.types import ObjectFrame

__all__ = [
    "MAX_MODEL_POINTS",
    "FusedObject",
    "POINT_STEP",
    "ObjectModel",
    "ObjectModelCache",
    "foreground_points",
    "fuse_object",
    "fused_object_points",
    "sampling_step",
    "voxel_subsample",
]

POINT_STEP = 2  # every 2nd row and column of a keyframe: dense enough to fill a silhouette
MAX_MODEL_POINTS = 4096  # points projected twice per frame: bounds the per-frame cost
_MIN_CONFIDENCE_RATIO = 0.5  # of the keyframe's median masked confidence (drops flying pixels)
_FUSED_POINTS = 16384  # fused points sampled per map (the model keeps MAX_MODEL_POINTS of them)
_ANCHOR_RADII = 2.0  # fused points lie within this many radii of the first keyframe's object
_BORDER_SHARE = 0.25  # keyframe 0's box border: this share of its width (height) along each edge
_CORNER_SHARE = 0.15  # keyframe 0's box corners: squares of this share of its width and height
# 3D components link points up to ~this many sample spacings or this share of the object's
# width apart, whichever is more (a round object's rim, sampled at a grazing angle, is sparse)
_LINK_SPACINGS = 2.0
_LINK_OF_EXTENT = 0.1


@dataclass(frozen=True)
class _Foreground:
    """One keyframe's foreground samples: world ``points`` [N, 3], their pixel ``rows`` and
    ``cols`` [N], the depth ``d_c`` and lateral extent ``lateral`` of the rule (world units) and
    ``spacing``: the distance between neighbouring samples at ``d_c`` (world units)."""

    points: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    lateral: float
    spacing: float


_NO_FOREGROUND = _Foreground(np.empty((0, 3)), np.empty(0, np.int64), np.empty(0, np.int64),
                             0.0, 0.0)


def _foreground(keyframe: Keyframe, step: int) -> _Foreground:
    local = keyframe.local_points[::step, ::step].astype(np.float64)
    confidence = keyframe.confidence_map[::step, ::step]
    selected = (
        np.ones(local.shape[:2], dtype=bool) if keyframe.mask is None
        else keyframe.mask[::step, ::step].copy()
    )  # fmt: skip
    selected &= np.isfinite(local).all(axis=-1) & (local[..., 2] > 0)
    if not selected.any():
        return _NO_FOREGROUND
    selected &= confidence >= _MIN_CONFIDENCE_RATIO * float(np.median(confidence[selected]))
    rows, cols = np.nonzero(selected)
    if rows.size == 0:
        return _NO_FOREGROUND
    depth = local[rows, cols, 2]
    centre_r, centre_c = (rows.min() + rows.max()) / 2.0, (cols.min() + cols.max()) / 2.0
    middle = (np.abs(rows - centre_r) <= (rows.max() - rows.min()) / 4.0) & (
        np.abs(cols - centre_c) <= (cols.max() - cols.min()) / 4.0
    )
    d_c = float(np.median(depth[middle] if middle.any() else depth))
    slope_x, slope_y = local[rows, cols, 0] / depth, local[rows, cols, 1] / depth
    lateral = d_c * max(float(np.ptp(slope_x)), float(np.ptp(slope_y)))
    spacing = d_c * float(np.ptp(slope_x)) / max(int(np.ptp(cols)), 1)  # one sample step
    keep = np.abs(depth - d_c) <= max(lateral, 1e-9)
    points = local[rows[keep], cols[keep]]
    R, t = keyframe.T_world_cam[:3, :3], keyframe.T_world_cam[:3, 3]
    return _Foreground(points @ R.T + t, rows[keep] * step, cols[keep] * step, lateral, spacing)


def foreground_points(keyframe: Keyframe, *, step: int = POINT_STEP) -> np.ndarray:
    """World points [N, 3] of ``keyframe``'s masked, confident, foreground pixels (every
    ``step``-th row and column); all pixels count as masked without a mask. See the module
    docstring for the foreground rule."""
    return _foreground(keyframe, step).points


def _planes_around(keyframe: Keyframe, first: _Foreground) -> SupportPlanes | None:
    """The support planes of keyframe 0 (``object_separation.find_planes``) from its foreground
    samples (every pixel: ``first`` has step 1): border, middle and corners are judged in the
    box of those samples."""
    rows, cols = first.rows, first.cols
    if rows.size == 0:
        return None
    r0, r1, c0, c1 = rows.min(), rows.max(), cols.min(), cols.max()
    band_r, band_c = _BORDER_SHARE * (r1 - r0), _BORDER_SHARE * (c1 - c0)
    border = ((rows - r0 <= band_r) | (r1 - rows <= band_r)
              | (cols - c0 <= band_c) | (c1 - cols <= band_c))
    middle = (np.abs(rows - (r0 + r1) / 2.0) <= (r1 - r0) / 4.0) & (
        np.abs(cols - (c0 + c1) / 2.0) <= (c1 - c0) / 4.0)
    size_r, size_c = _CORNER_SHARE * (r1 - r0), _CORNER_SHARE * (c1 - c0)
    top, bottom = rows - r0 <= size_r, r1 - rows <= size_r
    left, right = cols - c0 <= size_c, c1 - cols <= size_c
    corners = [top & left, top & right, bottom & left, bottom & right]
    corner_pixels = int((np.floor(size_r) + 1) * (np.floor(size_c) + 1))
    R, t = keyframe.T_world_cam[:3, :3], keyframe.T_world_cam[:3, 3]
    return find_planes(first.points, border, middle, corners, corner_pixels, t, -R[:, 1],
                       first.lateral)


@dataclass(frozen=True)
class FusedObject:
    """The fused object points [N, 3] (world) and the planes they were separated from."""

    points: np.ndarray
    planes: SupportPlanes | None


def fuse_object(keyframes: Sequence[Keyframe], *, step: int = POINT_STEP) -> FusedObject:
    """All keyframes' foreground points, separated from the planes around keyframe 0's object
    and from its neighbours (``object_separation``), within the anchor ball of keyframe 0's
    (see the module docstring)."""
    chunks = [_foreground(kf, step) for kf in keyframes]
    if not chunks or len(chunks[0].points) == 0:
        found = [c.points for c in chunks]
        return FusedObject(np.concatenate(found) if found else np.empty((0, 3)), None)
    # every pixel of keyframe 0 for the planes: a tight box shows the desk in its corners only
    planes = _planes_around(keyframes[0], _foreground(keyframes[0], 1))
    kept = [c.points if planes is None else c.points[drop_behind(c.points, planes)]
            for c in chunks]
    anchor = kept[0] if len(kept[0]) else chunks[0].points
    centre = anchor.mean(axis=0)
    radius = float(np.quantile(np.linalg.norm(anchor - centre, axis=1), 0.98))
    points = np.concatenate(kept)
    seeds = np.zeros(len(points), dtype=bool)
    seeds[: len(kept[0])] = True
    inside = np.linalg.norm(points - centre, axis=1) <= _ANCHOR_RADII * max(radius, 1e-12)
    points, seeds = points[inside], seeds[inside]
    link = max(_LINK_SPACINGS * chunks[0].spacing, _LINK_OF_EXTENT * chunks[0].lateral)
    if link > 0 and seeds.any():
        points = points[object_component(points, seeds, link)]
    return FusedObject(points, planes)


def fused_object_points(keyframes: Sequence[Keyframe], *, step: int = POINT_STEP) -> np.ndarray:
    """``fuse_object``'s points [N, 3] (world; N may be 0)."""
    return fuse_object(keyframes, step=step).points


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
        fused = fuse_object(kf_map.keyframes, step=sampling_step(kf_map.keyframes))
        points_all = fused.points
        if len(points_all) == 0:
            return None
        keyframe0 = kf_map.keyframes[0].T_world_cam
        planes = fused.planes
        if planes is not None and planes.support is not None:
            T_world_object, extent = _standing_frame(
                points_all, planes.planes[planes.support], planes.threshold, keyframe0)
            centre = T_world_object[:3, 3].copy()
            up: np.ndarray | None = T_world_object[:3, 2].copy()
        else:  # floating: keyframe 0's axes, principal axes of the points, their mean
            centre = points_all.mean(axis=0)
            T_world_object = np.eye(4)
            T_world_object[:3, :3] = keyframe0[:3, :3]
            T_world_object[:3, 3] = centre
            T_object_world = np.linalg.inv(T_world_object)
            extent = OrientedBox.fit(points_all @ T_object_world[:3, :3].T + T_object_world[:3, 3])
            up = None
        points = voxel_subsample(points_all, MAX_MODEL_POINTS)
        points.setflags(write=False)
        frame = ObjectFrame(T_world_object, extent, int(len(points_all)), kf_map.generation, up)
        return cls(points, centre, frame)


_ANGLE_STEPS = 90  # candidate footprint orientations, 1 degree apart over 90 degrees
# of the points on each side of each axis: every keyframe's points carry its own pose error, so
# the fused faces are blurred by it (1 % would set the extent 2-3 pose errors out); the faces of
# a box-like object hold far more than 5 % of the points, a round object loses ~1 % of its size
_TRIM = 0.05
_TOUCH_SHARE = 0.1  # the object stands on the plane if its lowest points are this close (of height)


def _standing_frame(
    points: np.ndarray, support: Plane3, threshold: float, T_world_keyframe0: np.ndarray
) -> tuple[np.ndarray, OrientedBox]:
    """(T_world_object, extent) of an object standing on ``support``: z = the plane's normal
    (up); x = keyframe 0's camera x laid onto the plane (stable across rebuilds); origin at the
    centre of the extent. The extent is the smallest-area footprint rectangle over 1-degree
    turns (a footprint's principal axes are undefined for a square, and a box-shaped object is
    the common case), holding all but 5 % of the points on each side, from the plane (when the
    lowest points are near it: the part hidden by the support is still object) to the top."""
    up = support.normal
    x = T_world_keyframe0[:3, 0] - (T_world_keyframe0[:3, 0] @ up) * up
    if np.linalg.norm(x) < 1e-6:  # keyframe 0 looked straight down: take its y instead
        x = T_world_keyframe0[:3, 1] - (T_world_keyframe0[:3, 1] @ up) * up
    x /= np.linalg.norm(x)
    axes = np.stack([x, np.cross(up, x), up], axis=1)  # right-handed, z = up
    height = support.distance(points)
    flat = points @ axes[:, :2]  # [N, 2] footprint coordinates
    angles = np.radians(np.arange(_ANGLE_STEPS))
    cos, sin = np.cos(angles), np.sin(angles)
    turns = np.stack([np.stack([cos, -sin], 1), np.stack([sin, cos], 1)], 1)  # [A, 2, 2]
    # the trimmed extremes by partial sorting (one pass over [A, N, 2], no interpolation)
    k_low, k_high = int(_TRIM * (len(flat) - 1)), int(round((1.0 - _TRIM) * (len(flat) - 1)))
    parted = np.partition(flat @ turns, [k_low, k_high], axis=1)
    lows, highs = parted[:, k_low], parted[:, k_high]  # [A, 2] each
    best = int(np.argmin(np.prod(highs - lows, axis=1)))
    angle, low, high = float(angles[best]), lows[best], highs[best]
    bottom, top = np.quantile(height, [_TRIM, 1.0 - _TRIM])
    if bottom <= max(_TOUCH_SHARE * (top - bottom), 3.0 * threshold):
        bottom = 0.0
    c, s = np.cos(angle), np.sin(angle)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    middle_flat = turn[:2, :2] @ ((low + high) / 2.0)  # footprint centre, unturned
    on_plane = -support.offset * up  # the plane's point nearest the world origin
    centre = on_plane + axes[:, :2] @ middle_flat + up * (bottom + top) / 2.0
    T_world_object = np.eye(4)
    T_world_object[:3, :3] = axes
    T_world_object[:3, 3] = centre
    T_object_box = np.eye(4)
    T_object_box[:3, :3] = turn
    half = np.array([*(high - low) / 2.0, (top - bottom) / 2.0])
    return T_world_object, OrientedBox(T_object_box, half)


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

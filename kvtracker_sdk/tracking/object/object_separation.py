"""Separating the object from what it stands on and what stands beside it.

A box (or a loosely predicted mask) around a mug on a desk also covers the desk at the mug's
depth, and sometimes part of the cup beside it. The depth foreground rule of ``object_model``
cannot tell them apart (they lie at the object's depth), so two geometric filters follow it:

1. **Support planes** (``find_planes``): a robust plane fit (RANSAC, then least squares on the
   inliers) over the *border* of keyframe 0's box — the band along its edges, where the desk and
   a wall behind the object show and the object itself only touches. Up to two planes are kept
   (a desk, and a wall behind the object), each only when it holds a large share of the border
   and the box's middle lies in front of it (the object stands on it, not the other way round).
   Every keyframe's points on or behind a plane are dropped (``drop_behind``); the plane is
   re-seated per keyframe on that keyframe's own points near it, so that a keyframe's pose error
   does not leave a sliver of desk above the threshold. The plane whose normal points most
   "up" in keyframe 0's image (towards -y, the way a hand-held camera is held) and clearly so is
   the **support plane**: its normal is the object frame's up.

   Why planes rather than colour or a learned segmenter: the map already holds metric-consistent
   points for every masked pixel, a desk or a wall is the dominant plane around an object in
   almost every AR scene, and RANSAC is cheap and needs no model. Why the box's border rather
   than its surroundings: in object mode the network only sees the masked frame (black
   elsewhere), so points outside the mask are not measurements.

2. **Connected components in 3D** (``object_component``): with the planes gone, the object and
   its neighbours are islands of points. The points are put on a voxel grid (cells of half the
   linking distance the caller chooses) and labelled with 26-connectivity
   (``scipy.ndimage.label``, rather than a k-d tree's pair list: one pass over a small dense
   grid); the component holding most of keyframe 0's points is the object. Neighbours further
   away than 3.5 cells stay separate; objects that touch merge (a limit).

Thresholds are relative (map units are not metres): the plane threshold is 3 % of the object's
lateral extent in keyframe 0 (or three residual standard deviations of the fit, if larger).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

__all__ = ["Plane3", "SupportPlanes", "drop_behind", "find_planes", "object_component"]

_BORDER = 0.25  # share of the box's width (height) along each edge that counts as its border
_HYPOTHESES = 256  # RANSAC samples per plane (fixed seed: the same map gives the same planes)
_MIN_SHARE = 0.02  # a plane explains at least this share of the border points (a tight box
# shows the desk in its corners only)
_ROUNDS = 6  # planes tried (an object's own faces are tried and set aside first)
_MAX_PLANES = 2  # a desk and a wall
_MIN_INLIERS = 20
_IN_FRONT_SHARE = 0.5  # of the box's middle points, in front of a plane by more than tau
_THRESHOLD_OF_EXTENT = 0.03  # plane threshold: 3 % of keyframe 0's lateral object extent
_RESEAT_BAND = 4.0  # a keyframe's points within this many thresholds re-seat the plane
_MIN_RESEAT = 8
_CORNER_SHARE = 0.3  # a plane fills at least this share of one corner square of the box
_UP_COSINE = 0.5  # support plane: normal at most 60 degrees from keyframe 0's image "up"
_CELLS_PER_LINK = 2.0  # the component voxel is half the linking distance
_MAX_GRID_CELLS = 8_000_000


@dataclass(frozen=True)
class Plane3:
    """``normal . x + offset = 0`` (world), ``normal`` unit and pointing to the object's side."""

    normal: np.ndarray
    offset: float

    def distance(self, points: np.ndarray) -> np.ndarray:
        """[N] signed distance of ``points`` [N, 3]: > 0 on the object's side."""
        return points @ self.normal + self.offset


@dataclass(frozen=True)
class SupportPlanes:
    """The planes found around keyframe 0's object: ``planes`` (at most two), ``threshold``
    (world units: points closer than this to a plane are on it) and ``support`` (index of the
    plane the object stands on, None if none is clearly below it)."""

    planes: tuple[Plane3, ...]
    threshold: float
    support: int | None

    @property
    def up(self) -> np.ndarray | None:
        """The support plane's unit normal (world), pointing away from it; None without one."""
        return None if self.support is None else self.planes[self.support].normal


def _fit_plane(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane (unit normal, offset) through ``points`` [N >= 3, 3]."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    normal = vt[-1]
    return normal, -float(normal @ centre)


def _ransac(points: np.ndarray, tau: float, rng: np.random.Generator) -> np.ndarray:
    """bool [N]: inliers (within ``tau``) of the best of ``_HYPOTHESES`` three-point planes."""
    picks = rng.integers(0, len(points), size=(_HYPOTHESES, 3))
    a, b, c = points[picks[:, 0]], points[picks[:, 1]], points[picks[:, 2]]
    normals = np.cross(b - a, c - a)
    norms = np.linalg.norm(normals, axis=1)
    good = norms > 1e-12
    normals, a = normals[good] / norms[good, None], a[good]
    if len(normals) == 0:
        return np.zeros(len(points), dtype=bool)
    offsets = -np.einsum("ij,ij->i", normals, a)
    counts = np.zeros(len(normals), dtype=np.int64)
    for start in range(0, len(normals), 32):  # [32, N] residuals at a time: bounded memory
        stop = start + 32
        residual = np.abs(normals[start:stop] @ points.T + offsets[start:stop, None])
        counts[start:stop] = (residual <= tau).sum(axis=1)
    best = int(np.argmax(counts))
    return np.abs(points @ normals[best] + offsets[best]) <= tau


def find_planes(
    points: np.ndarray, border: np.ndarray, middle: np.ndarray, corners: list[np.ndarray],
    corner_pixels: int, camera_centre: np.ndarray, image_up: np.ndarray, lateral_extent: float,
) -> SupportPlanes | None:
    """Planes around keyframe 0's object (see the module docstring), or None if none is found.

    ``points`` [N, 3]: keyframe 0's foreground points (world); ``border``, ``middle``: bool [N],
    the points whose pixels lie along the box's edges / in its middle half; ``corners``: four
    bool [N], the points in each corner square of the box, ``corner_pixels`` pixels each (kept
    or not); ``camera_centre`` [3] and ``image_up`` [3] (unit: keyframe 0's -y axis), world;
    ``lateral_extent``: the object's width at its depth (world units), which scales the
    threshold.

    A plane is kept only if the box's middle lies in front of it (not one of the object's own
    faces) and it fills at least 30 % of one of the box's corners (it extends past the object:
    a round object's rim, which a plane also fits, reaches the box's edges but not its corners).
    """
    tau = _THRESHOLD_OF_EXTENT * lateral_extent
    candidates = points[border]
    total = len(candidates)
    if total < _MIN_INLIERS or tau <= 0:
        return None
    rng = np.random.default_rng(0)
    planes: list[Plane3] = []
    spreads: list[float] = []
    for _ in range(_ROUNDS):  # the object's own faces come first when it fills the box
        if len(planes) == _MAX_PLANES or len(candidates) < _MIN_INLIERS:
            break
        inliers = _ransac(candidates, tau, rng)
        if inliers.sum() < max(_MIN_INLIERS, _MIN_SHARE * total):
            break
        normal, offset = _fit_plane(candidates[inliers])
        if normal @ camera_centre + offset < 0:  # orient towards the camera: the object's side
            normal, offset = -normal, -offset
        plane = Plane3(normal, offset)
        residual = plane.distance(candidates)
        on_plane = np.abs(residual) <= tau
        candidates = candidates[~on_plane]
        if np.mean(plane.distance(points[middle]) > tau) < _IN_FRONT_SHARE:
            continue  # the box's middle is not in front of it: one of the object's faces
        on_plane_all = np.abs(plane.distance(points)) <= tau
        if max(int((on_plane_all & corner).sum()) for corner in corners) < (
                _CORNER_SHARE * corner_pixels):
            continue  # it does not reach past the object: a rim, not a desk or a wall
        planes.append(plane)
        spreads.append(float(np.std(residual[on_plane])))
    if not planes:
        return None
    threshold = max(tau, 3.0 * max(spreads))
    ups = [float(p.normal @ image_up) for p in planes]
    support = int(np.argmax(ups)) if max(ups) >= _UP_COSINE else None
    return SupportPlanes(tuple(planes), threshold, support)


def _seat_offset(distance: np.ndarray, threshold: float) -> float:
    """How far one keyframe's own view of a plane lies from it: the densest slice (half a
    threshold thick) of its points within ``_RESEAT_BAND`` thresholds, refined by their median;
    0 if too few points are near. The densest slice, not the median of the band: an object 2 cm
    from a wall puts its own points in the band, but a plane seen over an area is denser."""
    band = _RESEAT_BAND * threshold
    near = distance[np.abs(distance) <= band]
    if len(near) < _MIN_RESEAT:
        return 0.0
    counts, edges = np.histogram(near, bins=max(1, int(round(4.0 * _RESEAT_BAND))),
                                 range=(-band, band))
    peak = int(np.argmax(counts))
    centre = (edges[peak] + edges[peak + 1]) / 2.0
    slice_ = near[np.abs(near - centre) <= threshold / 2.0]
    return float(np.median(slice_)) if len(slice_) >= _MIN_RESEAT else 0.0


def drop_behind(points: np.ndarray, planes: SupportPlanes) -> np.ndarray:
    """bool [N]: which of one keyframe's world ``points`` [N, 3] lie in front of every plane by
    more than the threshold, each plane first re-seated on this keyframe's own view of it
    (``_seat_offset``: a keyframe's pose error moves the plane it saw by as much)."""
    keep = np.ones(len(points), dtype=bool)
    for plane in planes.planes:
        distance = plane.distance(points)
        distance = distance - _seat_offset(distance, planes.threshold)
        keep &= distance > planes.threshold
    return keep


def object_component(points: np.ndarray, seeds: np.ndarray, link: float) -> np.ndarray:
    """bool [N]: the points of ``points`` [N, 3] in the 3D connected component (26-connected
    voxels of ``link / 2``) that holds most of the ``seeds`` (bool [N], keyframe 0's points)."""
    if len(points) == 0 or not seeds.any():
        return np.zeros(len(points), dtype=bool)
    low = points.min(axis=0)
    cell = max(link / _CELLS_PER_LINK, 1e-12)
    span = np.ptp(points, axis=0)
    while np.prod(np.floor(span / cell) + 1) > _MAX_GRID_CELLS:  # stray far points: coarser
        cell *= 1.5
    cells = np.floor((points - low) / cell).astype(np.int64)
    grid = np.zeros(tuple(cells.max(axis=0) + 1), dtype=bool)
    grid[cells[:, 0], cells[:, 1], cells[:, 2]] = True
    labels, _ = ndimage.label(grid, structure=np.ones((3, 3, 3), dtype=bool))
    point_labels = labels[cells[:, 0], cells[:, 1], cells[:, 2]]
    best = int(np.bincount(point_labels[seeds]).argmax())
    return point_labels == best

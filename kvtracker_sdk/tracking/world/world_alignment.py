"""Making the world frame metric and gravity-aligned: scale sources, the up direction, and the
transforms that re-express a map in the aligned world.

The world frame is kept by the gauge (``gauge.py``): every rebuild is aligned to the previous map,
so a transform applied to the current map once carries over to every later map. A
**world transform** ``W`` (a Sim(3) about the world origin, new world <- old world) re-expresses
the map: keyframe poses ``T -> W ∘ T``, local points scaled by ``W.scale``, gauge ``W ∘ gauge``.
The ``Tracker`` sends a ``WorldFrameChangedEvent`` carrying ``W`` so that the app can move its
anchors; ``MapKeeper.transform_world`` applies it to the map and to a rebuild in flight.

Scale sources (``ScaleSource``), strongest first:

* **depth**: a mapping pass's predicted depth is fitted to the keyframes' sensor depth
  (``metric_scale.py``). The first map with a depth frame is metric from its first pass; a world
  made before depth arrived is rescaled once (event METRIC_SCALE); from then on every rebuild takes
  its scale from the sensor (``RebuildRequest.anchor_to_depth``), so the scale cannot drift.
* **known size**: the app states a length (the object's height, or the distance between two world
  points); the world is rescaled once so that it measures that (event METRIC_SCALE), and the gauge
  keeps the scale across rebuilds. In a world already metric by depth the statement is only
  reported (``MapStatus.scale_estimates``) as a check, never applied.

Gravity: each frame's gravity reading (camera frame, pointing down) rotated by the frame's tracked
pose is one sample of "down" in the world; the mean of the unit samples estimates it. The world is
levelled as soon as a map and one sample exist, then again each time the sample count has doubled,
the estimate moved by more than ``RELEVEL_DEG`` and it is more certain than the estimate the world
was levelled to (a handful of events over a long run; a reloaded map keeps its levelling until
this session's readings beat it). Levelling keeps the heading: the new x axis is keyframe 0's viewing
direction made horizontal (once levelled, the current x axis), so yaw stays keyframe 0's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from kvtracker_sdk.cache.keyframe_map import Keyframe, KeyframeMap
from kvtracker_sdk.errors import InputError, StateError
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.tracking.mapping.map_builder import RebuildOutcome
from kvtracker_sdk.tracking.object.object_model import fused_object_points
from kvtracker_sdk.world import (
    GravityEstimate,
    MapWorld,
    ScaleEstimate,
    ScaleSource,
    WorldAlignment,
)

__all__ = [
    "GravityEstimator",
    "RELEVEL_DEG",
    "WorldAligner",
    "WorldChange",
    "level_rotation",
    "measured_height",
    "pixel_angle",
    "transform_map",
]

RELEVEL_DEG = 0.05  # re-level only for a change an app could notice over a room (~1 mm per m)
# A single reading's own error cannot be measured from itself: a MEMS accelerometer at rest with
# a tracked pose is good to about half a degree, which an estimate of one sample reports.
_SINGLE_SAMPLE_DEG = 0.5
_MIN_SPREAD_SAMPLES = 10
_HEIGHT_TRIM = 0.001  # object height: the extent between these quantiles (stray points cut)


@dataclass(frozen=True)
class WorldChange:
    """A world transform to apply: ``transform`` (new world <- old), why, and the new flags."""

    transform: Sim3
    reason: WorldAlignment
    world: MapWorld


def transform_map(kf_map: KeyframeMap, transform: Sim3, *, generation: int,
                  world: MapWorld) -> KeyframeMap:
    """``kf_map`` re-expressed in the world ``transform`` maps to (new world <- old world)."""
    scale = np.float32(transform.scale)
    keyframes = tuple(
        replace(kf, T_world_cam=transform.apply_to_pose(kf.T_world_cam),
                local_points=kf.local_points * scale if transform.scale != 1.0
                else kf.local_points)
        for kf in kf_map.keyframes
    )
    return replace(kf_map, keyframes=keyframes, gauge=transform @ kf_map.gauge,
                   generation=generation, world=world)


def level_rotation(up: np.ndarray, heading: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """3x3 rotation (new <- old) taking ``up`` to +z, with the new x axis along ``heading`` made
    horizontal (``fallback`` when ``heading`` is within ~6 degrees of vertical)."""
    z = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    for candidate in (heading, fallback):
        h = np.asarray(candidate, dtype=np.float64)
        horizontal = h - (h @ z) * z
        if np.linalg.norm(horizontal) > 0.1:
            x = horizontal / np.linalg.norm(horizontal)
            return np.stack([x, np.cross(z, x), z])  # rows: the new axes in old coordinates
    raise InputError("cannot level: heading and fallback both point along gravity")


def measured_height(
    points: np.ndarray, axis: np.ndarray, *, camera_centre: np.ndarray, pixel_angle: float
) -> tuple[float, float]:
    """(extent of ``points`` [N, 3] along unit ``axis``, its uncertainty), both world units.

    The extent between the 0.1 % and 99.9 % quantiles (a few stray points at either end, which
    min/max would follow, do not count), plus one pixel's footprint at the extreme points'
    distance from ``camera_centre`` (``pixel_angle`` radians per pixel): every point sits at its
    pixel's centre, half a pixel inside the object's outline on each side. Uncertainty: how far
    the 0.5 % / 99.5 % extent lies from it, and at least half a pixel's footprint (the outline is
    known to a pixel at each end). A smooth round outline (a ball) measures short by more than
    that: its outermost pixels see the surface at a grazing angle, nearer than its rim.
    """
    heights = points @ axis
    low, high, low5, high5 = np.quantile(heights, [_HEIGHT_TRIM, 1.0 - _HEIGHT_TRIM,
                                                  5 * _HEIGHT_TRIM, 1.0 - 5 * _HEIGHT_TRIM])
    ends = points[(heights <= low) | (heights >= high)]
    distance = float(np.median(np.linalg.norm(ends - camera_centre, axis=1)))
    footprint = pixel_angle * distance
    spread = abs(float(high - low) - float(high5 - low5))
    return float(high - low) + footprint, math.hypot(spread, 0.5 * footprint)


def pixel_angle(keyframe: Keyframe) -> float:
    """Radians per pixel of a keyframe's model image, from its local points' ray slopes (the
    median step of y/z between neighbouring rows: no intrinsics needed)."""
    local = keyframe.local_points
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = local[..., 1] / local[..., 2]
    steps = np.abs(np.diff(slope, axis=0))
    steps = steps[np.isfinite(steps)]
    return float(np.median(steps)) if steps.size else 0.0


class GravityEstimator:
    """The mean of unit "down" samples in the current world frame (see the module docstring).

    The sum and the count are one tuple, replaced whole: ``MapStatus`` reads them from other
    threads without the tracker's lock."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._sum: tuple[np.ndarray, int] = (np.zeros(3), 0)
        self.count_at_check = 0  # samples at the last levelling decision

    @property
    def count(self) -> int:
        return self._sum[1]

    def add(self, down_world: np.ndarray) -> None:
        total, count = self._sum
        self._sum = (total + down_world / np.linalg.norm(down_world), count + 1)

    def rotate(self, rotation: np.ndarray) -> None:
        """The world was rotated (new <- old): keep the samples in the new world's coordinates."""
        total, count = self._sum
        self._sum = (rotation @ total, count)

    @property
    def up(self) -> np.ndarray:
        total = self._sum[0]
        return -total / np.linalg.norm(total)

    def uncertainty_deg(self) -> float:
        """RMS angular error of the mean direction: the per-sample mean square angle 2 (1 - R)
        (R the mean resultant length; small-angle spherical statistics) over the count. A few
        samples cannot measure their own spread: below ``_MIN_SPREAD_SAMPLES`` the per-sample
        error is taken as at least ``_SINGLE_SAMPLE_DEG``."""
        total, n = self._sum
        resultant = float(np.linalg.norm(total)) / n
        spread = math.degrees(math.sqrt(max(2.0 * (1.0 - resultant), 0.0) * n / max(n - 1, 1)))
        if n < _MIN_SPREAD_SAMPLES:
            spread = max(spread, _SINGLE_SAMPLE_DEG)
        return spread / math.sqrt(n)

    def estimate(self, aligned: bool) -> GravityEstimate | None:
        snapshot = GravityEstimator()
        snapshot._sum = self._sum  # one consistent (sum, count) pair
        if snapshot.count == 0:
            return None
        up = snapshot.up
        tilt = math.degrees(math.acos(float(np.clip(up[2], -1.0, 1.0))))
        return GravityEstimate(up, snapshot.uncertainty_deg(), tilt, snapshot.count, aligned)


class WorldAligner:
    """One tracker's scale sources and gravity: decides the world transforms. The tracker's lock
    guards every call but ``estimates`` and ``gravity_estimate`` (``MapStatus``: they read values
    replaced whole). It never changes a map itself; ``FrameLoop`` applies what it returns
    through ``MapKeeper.transform_world``."""

    def __init__(self) -> None:
        self.gravity = GravityEstimator()
        self._estimates: dict[ScaleSource, ScaleEstimate] = {}
        self._object_height: tuple[float, float] | None = None  # (metres, 1-sigma) to apply

    def reset(self) -> None:
        """A new world frame (map dropped or loaded): its samples and statements are void."""
        self.gravity.reset()
        self._estimates = {}
        self._object_height = None

    def loaded(self, kf_map: KeyframeMap) -> None:
        """A saved map was installed: a new session of its world. Its recorded scale is reported
        (``frame_index`` None, no samples) until a source measures again."""
        self.reset()
        world = kf_map.world
        if world.metric:
            self._set_estimate(ScaleEstimate(
                world.scale_source, 1.0, world.scale_uncertainty or 0.0, 0, applied=True))

    def _set_estimate(self, estimate: ScaleEstimate) -> None:
        # replaced whole, never mutated: MapStatus reads it from other threads without the lock
        self._estimates = {**self._estimates, estimate.source: estimate}

    def estimates(self) -> tuple[ScaleEstimate, ...]:
        current = self._estimates
        return tuple(current[s] for s in ScaleSource if s in current)

    def gravity_estimate(self, kf_map: KeyframeMap | None) -> GravityEstimate | None:
        return self.gravity.estimate(kf_map is not None and kf_map.world.gravity_aligned)

    # ------------------------------------------------------------------ gravity
    def after_pose(
        self, kf_map: KeyframeMap, T_world_cam: np.ndarray, gravity: np.ndarray
    ) -> WorldChange | None:
        """A confidently tracked frame (world pose) with a gravity reading (camera frame): one
        more sample; a levelling when one is due."""
        self.gravity.add(T_world_cam[:3, :3] @ gravity)
        return self._levelling(kf_map)

    def _levelling(self, kf_map: KeyframeMap) -> WorldChange | None:
        g = self.gravity
        if g.count == 0:
            return None
        aligned = kf_map.world.gravity_aligned
        if aligned and g.count < 2 * max(g.count_at_check, 1):
            return None  # re-level only when the estimate rests on twice the samples
        g.count_at_check = g.count
        up = g.up
        tilt = math.degrees(math.acos(float(np.clip(up[2], -1.0, 1.0))))
        uncertainty = g.uncertainty_deg()
        levelled_to = kf_map.world.gravity_uncertainty_deg
        if aligned and (tilt <= RELEVEL_DEG or (
                levelled_to is not None and uncertainty >= levelled_to)):
            return None  # a change nobody would notice, or no better than the world's levelling
        eye = np.eye(3)
        # yaw stays keyframe 0's: its viewing direction (camera z, the unlevelled world's z) or,
        # once levelled, the world's x axis (that direction made horizontal)
        heading, fallback = (eye[0], eye[1]) if aligned else (eye[2], -eye[1])
        rotation = level_rotation(up, heading, fallback)
        world = replace(kf_map.world, gravity_aligned=True, gravity_uncertainty_deg=uncertainty)
        return WorldChange(Sim3(rotation, np.zeros(3), 1.0), WorldAlignment.GRAVITY, world)

    # ------------------------------------------------------------------ scale
    def after_rebuild(self, outcome: RebuildOutcome, kf_map: KeyframeMap) -> list[WorldChange]:
        """An accepted rebuild was installed (``kf_map``): record its depth fit and rescale a
        world that is not metric by depth yet."""
        changes: list[WorldChange] = []
        if outcome.request.previous is None:  # a new world frame: earlier samples are void
            self.gravity.reset()
        fit = outcome.depth_fit
        frame = outcome.request.candidate.frame_index
        if fit is not None:
            metres_per_unit = fit.scale / kf_map.gauge.scale
            anchored = kf_map.world.scale_source is ScaleSource.DEPTH
            self._set_estimate(ScaleEstimate(
                ScaleSource.DEPTH, metres_per_unit, fit.relative_uncertainty, fit.pixels,
                applied=True, frame_index=frame))
            if not anchored:
                world = replace(kf_map.world, scale_source=ScaleSource.DEPTH,
                                scale_uncertainty=fit.relative_uncertainty)
                changes.append(WorldChange(Sim3(np.eye(3), np.zeros(3), metres_per_unit),
                                           WorldAlignment.METRIC_SCALE, world))
                self._mark_known_size_unapplied()
        return changes

    def rescaled(self, factor: float) -> None:
        """The world was rescaled by ``factor``: re-express the estimates' metres per unit."""
        for estimate in list(self._estimates.values()):
            self._set_estimate(replace(estimate,
                                       metres_per_unit=estimate.metres_per_unit / factor))

    def _mark_known_size_unapplied(self) -> None:
        known = self._estimates.get(ScaleSource.KNOWN_SIZE)
        if known is not None:
            self._set_estimate(replace(known, applied=False))

    def state_length(
        self, kf_map: KeyframeMap | None, length_m: float, measured: float,
        measured_sigma: float, stated_sigma_m: float, frame_index: int | None,
    ) -> WorldChange | None:
        """The app says ``measured`` world units are ``length_m`` metres: an estimate, and the
        rescaling unless the world is metric by depth."""
        if kf_map is None:
            raise StateError("a known length needs a map: push frames until tracking starts")
        if not (math.isfinite(measured) and measured > 0):
            raise InputError(f"the measured length is {measured}: the points coincide")
        metres_per_unit = length_m / measured
        relative = math.hypot(stated_sigma_m / length_m, measured_sigma / measured)
        by_depth = kf_map.world.scale_source is ScaleSource.DEPTH
        self._set_estimate(ScaleEstimate(
            ScaleSource.KNOWN_SIZE, metres_per_unit, relative, 1, applied=not by_depth,
            frame_index=frame_index))
        if by_depth:
            return None
        world = replace(kf_map.world, scale_source=ScaleSource.KNOWN_SIZE,
                        scale_uncertainty=relative)
        return WorldChange(Sim3(np.eye(3), np.zeros(3), metres_per_unit),
                           WorldAlignment.METRIC_SCALE, world)

    def state_object_height(self, height_m: float, sigma_m: float) -> None:
        """Object mode: the object's height, applied once the map holds object points."""
        self._object_height = (height_m, sigma_m)

    def pending_object_height(
        self, kf_map: KeyframeMap | None, frame_index: int | None
    ) -> WorldChange | None:
        """Apply a stated object height if the map now holds object points."""
        if self._object_height is None or kf_map is None:
            return None
        keyframes = kf_map.keyframes
        points = fused_object_points(keyframes, step=1)  # every pixel: the outline matters
        if len(points) < 16:
            return None  # no object yet: try again after the next frame
        height_m, sigma_m = self._object_height
        self._object_height = None
        # "height": along up once levelled, else keyframe 0's image up (its camera's -y)
        axis = (np.array([0.0, 0.0, 1.0]) if kf_map.world.gravity_aligned
                else -keyframes[0].T_world_cam[:3, 1])
        measured, measured_sigma = measured_height(
            points, axis, camera_centre=keyframes[0].T_world_cam[:3, 3],
            pixel_angle=pixel_angle(keyframes[0]))
        return self.state_length(kf_map, height_m, measured, measured_sigma, sigma_m, frame_index)

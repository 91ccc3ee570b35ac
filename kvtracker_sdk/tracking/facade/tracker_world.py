"""``tracker.world``: the app states a known size, and the world becomes metric.

A thin view over the tracker's world alignment (``world/world_alignment.py``): it owns no state
and no lock of its own; each statement is validated first (InputError before anything changes),
then applied under the tracker's lock. A statement rescales the world about its origin and sends
``on_world_frame_changed`` (reason METRIC_SCALE) with the rescaling; a world already metric by
depth only records it (``map_status.scale_estimates``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from kvtracker_sdk.errors import InputError, StateError
from kvtracker_sdk.tracking.world.world_alignment import WorldChange
from kvtracker_sdk.types import Pose, TrackedPose

if TYPE_CHECKING:  # pragma: no cover
    from kvtracker_sdk.tracking.facade.tracker import Tracker

__all__ = ["TrackerWorld"]


class TrackerWorld:
    """Known sizes that make the world metric (``tracker.world``)."""

    __slots__ = ("_tracker",)

    def __init__(self, tracker: Tracker) -> None:
        self._tracker = tracker

    def set_known_distance(
        self, length_m: float, a: Any, b: Any, *, uncertainty_m: float = 0.0
    ) -> None:
        """The distance between two things the tracker reported is ``length_m`` metres: ``a``
        and ``b`` are world points [3] or poses (``Pose``/``TrackedPose``/4x4 ``T_world_cam``:
        their camera centres), in the current world. The world is rescaled at once; StateError
        without a map."""
        length, sigma = _checked_length(length_m, uncertainty_m)
        p, q = _world_point(a), _world_point(b)
        tracker = self._tracker
        with tracker._call():
            loop = tracker._loop
            self._apply(loop.aligner.state_length(
                tracker._keeper.map, length, float(np.linalg.norm(p - q)), 0.0, sigma,
                loop.snapshot.frame_index))

    def set_object_height(self, height_m: float, *, uncertainty_m: float = 0.0) -> None:
        """Object mode: the object's true height in metres. Once the map holds object points
        (at once, or after the next frames) the world is rescaled so that the object measures
        ``height_m`` along up (keyframe 0's image up before the world is levelled). StateError
        in scene mode (``set_known_distance`` there)."""
        height, sigma = _checked_length(height_m, uncertainty_m)
        tracker = self._tracker
        with tracker._call():
            if not tracker._object_mode:
                raise StateError("set_object_height needs object mode; use set_known_distance")
            aligner = tracker._loop.aligner
            aligner.state_object_height(height, sigma)
            self._apply(aligner.pending_object_height(
                tracker._keeper.map, tracker._loop.snapshot.frame_index))

    def _apply(self, change: WorldChange | None) -> None:
        """Under the tracker's lock: apply a world change and move object mode's region poses
        along (extrapolating across worlds would mix them)."""
        if change is not None:
            tracker = self._tracker
            tracker._loop.apply_world(change, tracker._loop.snapshot.frame_index)
            tracker._mode.forget_poses()


def _checked_length(length_m: Any, uncertainty_m: Any) -> tuple[float, float]:
    """(length, 1-sigma) in metres, validated: InputError unless finite, length > 0, sigma >= 0."""
    try:
        length, sigma = float(length_m), float(uncertainty_m)
    except (TypeError, ValueError, OverflowError) as exc:
        raise InputError(f"a known length must be numbers, got {length_m!r}") from exc
    if not (np.isfinite(length) and length > 0 and np.isfinite(sigma) and sigma >= 0):
        raise InputError(f"a known length needs length > 0 and uncertainty >= 0 (metres), got "
                         f"{length}, {sigma}")
    return length, sigma


def _world_point(value: Any) -> np.ndarray:
    """A world point [3] from a point, a ``Pose``/``TrackedPose`` or a 4x4 pose (its centre)."""
    if isinstance(value, TrackedPose):
        value = value.pose
    if isinstance(value, Pose):
        return np.asarray(value.translation, dtype=np.float64)
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"a known distance needs points [3] or poses, got {value!r}") from exc
    if array.shape == (4, 4):
        array = array[:3, 3]
    if array.shape != (3,) or not np.isfinite(array).all():
        raise InputError(f"a known distance needs finite points [3] or 4x4 poses, got {array!r}")
    return array

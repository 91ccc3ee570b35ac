"""``tracker.object``: what object mode tells the app about the object, and its segmenter.

A thin view over the tracker's object-mode strategy (``object/frame_mode.py``): it owns no state
and no lock of its own; members that touch the map or the strategy hold the tracker's lock. In
scene mode ``frame`` and ``region`` are None.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from kvtracker_sdk.errors import InputError
from kvtracker_sdk.tracking.object.segmenter import Segmenter
from kvtracker_sdk.types import ObjectFrame, ObjectRegion

if TYPE_CHECKING:  # pragma: no cover
    from kvtracker_sdk.tracking.facade.tracker import Tracker

__all__ = ["TrackerObject", "checked_segmenter"]


class TrackerObject:
    """The tracked object's frame and region, and the segmenter (``tracker.object``)."""

    __slots__ = ("_tracker",)

    def __init__(self, tracker: Tracker) -> None:
        self._tracker = tracker

    @property
    def frame(self) -> ObjectFrame | None:
        """Object mode: the object's frame and extent in the world frame (``ObjectFrame``: origin
        at the object centre; z along ``up``, the support plane's normal, for an object standing
        on one, else axes of keyframe 0; an oriented box of the fused object points); None in
        scene mode and before the map holds object points."""
        tracker = self._tracker
        if not tracker._object_mode:
            return None
        with tracker._call():
            return tracker._mode.object_frame(tracker._keeper.map)

    @property
    def region(self) -> ObjectRegion | None:
        """Object mode: the region of the last frame (``FrameResult.region``), None before one."""
        return self._tracker._mode.last_region

    def set_segmenter(self, segmenter: Segmenter | None) -> None:
        """Object mode: ask ``segmenter`` for the object's mask in every frame pushed without a
        mask or box, prompting it with the predicted region (None: use the prediction itself)."""
        checked = checked_segmenter(segmenter)
        with self._tracker._call():
            self._tracker._mode.segmenter = checked


def checked_segmenter(segmenter: Any) -> Segmenter | None:
    """``segmenter`` if it is a ``Segmenter`` or None; InputError otherwise."""
    if segmenter is not None and not isinstance(segmenter, Segmenter):
        raise InputError(f"segmenter must have a segment(image, prompt) method, got {segmenter!r}")
    return segmenter

"""What a tracking mode adds around the frame loop's step, at two fixed points.

``Tracker.push_frame`` calls its mode ``before_step`` (with the frame as checked on entry, a
``FrameInput``: which mask the frame is prepared with) and ``after_step`` (with the step's pose:
what the frame says about the object).
Scene mode (``SceneFrames``) adds nothing; object mode (``ObjectFrames``) keeps everything about
the object's region in one place: the predicted region or the segmenter's mask before the step, a
whole-frame search against a loaded object map, and after the step the region, the object's pose
in the camera, and the count of frames searched in vain. Following an object-mode frame to its
pose thus reads the facade, the frame's checks, this module (before the step), the frame's
preparation for the model, the frame loop, and this module again (after the step).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.tracking.core.frame_input import FrameInput
from kvtracker_sdk.tracking.object.object_region import RegionPropagator
from kvtracker_sdk.tracking.object.segmenter import Segmenter
from kvtracker_sdk.types import ObjectFrame, ObjectRegion

__all__ = ["FrameMode", "ObjectFrames", "ObjectObservation", "RegionInput", "SceneFrames"]


def _ms(since: float) -> float:
    return (time.perf_counter() - since) * 1e3


@dataclass(frozen=True)
class RegionInput:
    """What ``before_step`` decided for one frame: the mask it is prepared with."""

    mask: np.ndarray | None  # bool [H, W]: the app's, or the predicted / segmented / whole-frame
    # one; None: none (the app's box alone, or no region known yet)
    segmented: np.ndarray | None = None  # the segmenter's mask, if it was asked
    searching: bool = False  # tracked with the whole frame against a loaded map (no keyframe)
    prompt_ms: float = 0.0  # predicting the region and asking the segmenter


@dataclass(frozen=True)
class ObjectObservation:
    """What ``after_step`` found: the frame's object region and pose (object mode)."""

    region: ObjectRegion | None = None
    T_cam_object: np.ndarray | None = None
    object_frame: ObjectFrame | None = None
    search_exhausted: bool = False  # this frame made ``object.search_frames`` in vain in a row


_NOTHING = ObjectObservation()


class FrameMode:
    """Scene or object mode around the step; the base is scene mode's (nothing to add)."""

    segmenter: Segmenter | None = None

    @property
    def last_region(self) -> ObjectRegion | None:
        """The region of the last frame (None in scene mode and before one)."""
        return None

    def before_step(
        self, frame: FrameInput, index: int, kf_map: KeyframeMap | None, *, start: float
    ) -> RegionInput:
        """The mask to prepare ``frame`` with (``start``: when the step began, for its timing)."""
        return RegionInput(frame.mask)

    def after_step(
        self, regions_in: RegionInput, frame: FrameInput, index: int, kf_map: KeyframeMap | None,
        T_world_cam: np.ndarray | None, camera: Camera | None, timings: dict[str, float],
    ) -> ObjectObservation:
        """What the step (its valid pose ``T_world_cam`` or None, the input image's ``camera``)
        says about the object; adds its time to ``timings``."""
        return _NOTHING

    def object_frame(self, kf_map: KeyframeMap | None) -> ObjectFrame | None:
        return None

    def forget_poses(self) -> None:
        """The world frame was re-expressed: poses kept for prediction belong to the old one."""

    def reset(self) -> None:
        """A new session (reset, or a loaded map)."""


class SceneFrames(FrameMode):
    """Scene mode: frames are prepared as given, and a step says nothing about an object."""

    def __init__(self, segmenter: Segmenter | None = None) -> None:
        self.segmenter = segmenter  # kept for an app that sets one; scene mode never asks it


class ObjectFrames(FrameMode):
    """Object mode: the object's region before and after each step (``object_region``)."""

    def __init__(
        self, regions: RegionPropagator, segmenter: Segmenter | None, *, search_frames: int
    ) -> None:
        self.regions = regions
        self.segmenter = segmenter
        self._search_frames = search_frames
        self._searched = 0  # frames tracked unmasked in a row without finding the object

    @property
    def last_region(self) -> ObjectRegion | None:
        return self.regions.last

    def before_step(
        self, frame: FrameInput, index: int, kf_map: KeyframeMap | None, *, start: float
    ) -> RegionInput:
        """The mask to prepare the frame with: the app's, else the region predicted from the map
        (or the segmenter's mask), else, against a loaded map with no pose yet, the whole frame."""
        if frame.given:
            return RegionInput(frame.mask, prompt_ms=_ms(start))
        mask, segmented = self.regions.input_mask(frame, index, kf_map, self.segmenter)
        searching = mask is None and kf_map is not None  # a loaded map, no pose yet: search
        if searching:
            mask = np.ones(frame.size, dtype=bool)
        return RegionInput(mask, segmented, searching, _ms(start))

    def after_step(
        self, regions_in: RegionInput, frame: FrameInput, index: int, kf_map: KeyframeMap | None,
        T_world_cam: np.ndarray | None, camera: Camera | None, timings: dict[str, float],
    ) -> ObjectObservation:
        """The frame's region and the object's pose in its camera (``T_world_cam``: the step's
        valid pose, else None); counts a search that found nothing."""
        region_start = time.perf_counter()
        region, T_cam_object, object_frame = self.regions.observe(
            frame, index, kf_map, T_world_cam=T_world_cam, camera=camera,
            segmented=regions_in.segmented)
        timings["region"] = _ms(region_start) + (
            0.0 if regions_in.segmented is not None else regions_in.prompt_ms)
        missed = regions_in.searching and T_world_cam is None
        self._searched = self._searched + 1 if missed else 0
        return ObjectObservation(region, T_cam_object, object_frame,
                                 self._searched == self._search_frames)

    def object_frame(self, kf_map: KeyframeMap | None) -> ObjectFrame | None:
        return self.regions.object_frame(kf_map)

    def forget_poses(self) -> None:
        self.regions.forget_poses()

    def reset(self) -> None:
        self.regions.reset()
        self._searched = 0

"""``FrameLoop``: what the tracker does with one validated frame, and the state it keeps doing so.

Per frame: take a finished rebuild (``MapKeeper.collect``), track against the current map's KV
cache, map the raw pose into the world frame through the map's gauge, judge confidence
(``quality``), move through the state table (``states``), and maybe propose a keyframe. Events are
queued on the ``EventBus`` (the ``Tracker`` delivers them once its lock is released). Not
thread-safe on its own: the ``Tracker``'s lock guards every call.

Failures (``failures``): a tracking pass that raises or returns non-finite numbers gives a step
with ``error`` set and counts as a low-confidence frame; a failed mapping pass keeps the map. Both
are told once through ``on_backend_failed``. After a relocalisation timeout drops the map, the next
map must reach an absolute confidence floor (relaxed once after repeated rejections: reason
``RELAXED_FLOOR``), and its installation tells the app that the world frame changed
(``on_world_frame_changed``).
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import NamedTuple

import numpy as np

from kvtracker_sdk.backends.base import Backend
from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.config import TimeoutPolicy, TrackerConfig
from kvtracker_sdk.errors import TrackingFailedError
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.tracking.core.events import (
    BackendFailedEvent,
    EventBus,
    EventKind,
    MapUpdatedEvent,
    StateChangeEvent,
    WorldFrameChangedEvent,
)
from kvtracker_sdk.tracking.core.model_input import PreparedFrame
from kvtracker_sdk.tracking.core.quality import ConfidenceMonitor, frame_confidence
from kvtracker_sdk.tracking.loop.reporting import WorldFrameChange, failure_event, rebuild_events
from kvtracker_sdk.tracking.loop.states import TrackingEvent, next_state
from kvtracker_sdk.tracking.mapping.failures import MappingFailure, track_checked
from kvtracker_sdk.tracking.mapping.map_builder import RebuildCause, RebuildOutcome
from kvtracker_sdk.tracking.mapping.map_keeper import MapKeeper
from kvtracker_sdk.tracking.world.world_alignment import WorldAligner, WorldChange
from kvtracker_sdk.types import Pose, StateReason, TrackedPose, TrackerSnapshot, TrackingState
from kvtracker_sdk.world import WorldAlignment

__all__ = ["FrameLoop", "Step"]

_S, _R, _E = TrackingState, StateReason, TrackingEvent


def _ms(since: float) -> float:
    return (time.perf_counter() - since) * 1e3


class Step(NamedTuple):
    """What processing one frame gave."""

    pose: Pose | None
    valid: bool
    confidence: float | None
    keyframe_id: int | None = None
    error: TrackingFailedError | None = None


_NO_POSE = Step(None, False, None)


class FrameLoop:
    """The per-frame pipeline, the state snapshot and the map keeper of one tracker."""

    def __init__(
        self, config: TrackerConfig, backend: Backend, events: EventBus, *, preprocessing: str
    ) -> None:
        """``preprocessing``: the name of the pipeline that prepares frames of new maps."""
        self.config, self.backend, self.events = config, backend, events
        self.keeper = MapKeeper(config, preprocessing=preprocessing)
        self.monitor = ConfidenceMonitor.from_config(config.relocalization)
        self.snapshot = TrackerSnapshot(_S.INIT, _R.NONE)  # replaced as a whole, never mutated
        self.failed_tracks = self._failed_tracks_in_row = 0
        self._world_change: WorldFrameChange | None = None  # a dropped world frame, not yet told
        self.predicted_K: np.ndarray | None = None  # the last tracked frame's network K (DA3)
        self.aligner = WorldAligner()  # metric scale and gravity (world_alignment)
        self.world_changes = 0  # world transforms applied so far (the tracker's region poses)

    @property
    def state(self) -> TrackingState:
        return self.snapshot.state

    @property
    def reason(self) -> StateReason:
        return self.snapshot.reason

    # ------------------------------------------------------------------ one frame
    def step(
        self, frame: PreparedFrame, index: int, timings: dict[str, float],
        gravity: np.ndarray | None = None, *, keyframe_allowed: bool = True,
    ) -> Step:
        """Process frame ``index`` (``gravity``: its reading, camera frame, pointing down) and
        publish the new snapshot; ``keyframe_allowed`` False: the frame may not become a keyframe
        (its mask is not the object's)."""
        self.collect(index, timings)
        step = self._process(frame, index, timings, keyframe_allowed)
        if step.valid and (step.pose is None or not np.all(np.isfinite(step.pose.T_world_cam))):
            step = step._replace(valid=False)  # last line: a non-finite pose is never valid
        step = self._align_world(step, index, gravity)
        tracked = self.snapshot.pose
        if step.valid and step.pose is not None:
            tracked = TrackedPose(step.pose, index, frame.timestamp)
        self.snapshot = TrackerSnapshot(
            self.state, self.reason, index, frame.timestamp, tracked, self.generation
        )
        return step

    @property
    def generation(self) -> int:
        return self.keeper.status().generation

    # ------------------------------------------------------------------ world alignment
    def _align_world(self, step: Step, index: int, gravity: np.ndarray | None) -> Step:
        """Gravity sample and stated object height of this frame: levelling or rescaling the
        world when due (the step's pose follows into the new world)."""
        kf_map = self.keeper.map
        if kf_map is None:
            return step
        if gravity is not None and step.valid and step.pose is not None:
            level = self.aligner.after_pose(kf_map, step.pose.T_world_cam, gravity)
            if level is not None:
                step = self._moved_step(step, self.apply_world(level, index))
        # measured in the world as it is now (levelled first: "height" is along up)
        rescale = self.aligner.pending_object_height(self.keeper.map, index)
        if rescale is not None:
            step = self._moved_step(step, self.apply_world(rescale, index))
        return step

    @staticmethod
    def _moved_step(step: Step, transform: Sim3) -> Step:
        if step.pose is None:
            return step
        return step._replace(pose=Pose(transform.apply_to_pose(step.pose.T_world_cam)))

    def apply_world(self, change: WorldChange, index: int | None) -> Sim3:
        """Re-express the map (and the last pose) in the new world and tell the app."""
        previous = self.keeper.generation
        new_map = self.keeper.transform_world(change)
        W = change.transform
        self.world_changes += 1
        if change.reason is WorldAlignment.GRAVITY:
            self.aligner.gravity.rotate(W.rotation)
        if W.scale != 1.0:
            self.aligner.rescaled(W.scale)
        tracked = self.snapshot.pose
        if tracked is not None:
            tracked = replace(tracked, pose=Pose(W.apply_to_pose(tracked.pose.T_world_cam)))
        self.snapshot = replace(self.snapshot, pose=tracked, map_generation=new_map.generation)
        self.events.post(EventKind.MAP_UPDATED, MapUpdatedEvent.of(new_map, "world"))
        self.events.post(EventKind.WORLD_FRAME_CHANGED, WorldFrameChangedEvent(
            change.reason, previous, new_map.generation, index, W))
        return W

    def _process(
        self, frame: PreparedFrame, index: int, timings: dict[str, float], keyframe_allowed: bool
    ) -> Step:
        kf_map = self.keeper.map
        if kf_map is None:
            return self._bootstrap(frame, index, timings)
        start = time.perf_counter()
        try:
            pose, confidence = self._track(frame, kf_map, index)
        except TrackingFailedError as error:
            self._track_failed(error, index)
            return Step(None, False, None, error=error)
        finally:
            timings["track"] = _ms(start)
        verdict = self.monitor.update(confidence, relocalizing=self.state is _S.RELOCALIZING)
        self._react(verdict.lost, verdict.recovered, verdict.timed_out, index)
        if self.keeper.map is None:  # a timeout policy dropped the map
            if self.state is _S.MAPPING:
                return self._bootstrap(frame, index, timings)
            return Step(None, False, confidence)
        valid = self.state is _S.TRACKING and verdict.confident
        if valid and keyframe_allowed and self.keeper.wants_keyframe(pose.T_world_cam, index):
            keyframe_id = self.keeper.propose(self.backend, frame, index, pose.T_world_cam)
            outcome = self.collect(index, timings) if keyframe_id is not None else None
            if (
                isinstance(outcome, RebuildOutcome)
                and outcome.accepted
                and self.keeper.map is not None
                and outcome.request.candidate.keyframe_id == keyframe_id
            ):
                keyframe = self.keeper.map.keyframe(keyframe_id)
                return Step(Pose(keyframe.T_world_cam), True, confidence, keyframe_id)
        return Step(pose, valid, confidence)

    def _track(
        self, frame: PreparedFrame, kf_map: KeyframeMap, index: int
    ) -> tuple[Pose, float | None]:
        """The frame's world pose and confidence; TrackingFailedError if the backend failed."""
        tracked = track_checked(self.backend, frame.image, kf_map.cache, self.config.heads, index)
        self.predicted_K = tracked.intrinsics  # the network's K of the model image, if any
        try:
            with np.errstate(over="ignore", invalid="ignore"):  # overflow is refused just below
                pose = Pose(kf_map.gauge.apply_to_pose(tracked.pose))
        except ValueError as exc:  # a malformed pose from the backend
            raise TrackingFailedError(f"tracking frame {index} returned a bad pose") from exc
        if not np.all(np.isfinite(pose.T_world_cam)):  # a finite raw pose times a huge gauge
            raise TrackingFailedError(
                f"tracking frame {index}: the world pose is not finite (map gauge "
                f"scale {kf_map.gauge.scale!r})"
            )
        self._failed_tracks_in_row = 0
        return pose, frame_confidence(tracked.confidence, tracked.confidence_map, frame.mask)

    def _track_failed(self, error: TrackingFailedError, index: int) -> None:
        """Report a failed tracking pass; it counts as a low-confidence frame (no pose)."""
        self.failed_tracks += 1
        self._failed_tracks_in_row += 1
        self.events.post(EventKind.BACKEND_FAILED, BackendFailedEvent(
            "track", index, str(error), error, self._failed_tracks_in_row))
        verdict = self.monitor.update(0.0, relocalizing=self.state is _S.RELOCALIZING)
        self._react(verdict.lost, False, verdict.timed_out, index)

    def _bootstrap(self, frame: PreparedFrame, index: int, timings: dict[str, float]) -> Step:
        """No map: this frame starts the first map (or a new one) unless one is being built or
        a failed pass's backoff (or a rejected new map's wait) is running."""
        self.fire(_E.FRAME_WITHOUT_MAP, index)
        if not self.keeper.rebuilding and self.keeper.may_start(index):
            cause = RebuildCause.NEW_MAP if self.reason is _R.NEW_MAP else RebuildCause.BOOTSTRAP
            self.keeper.start_bootstrap(self.backend, frame, index, cause)
            self.collect(index, timings)
        if self.keeper.map is None:
            return _NO_POSE
        keyframe0 = self.keeper.map.keyframes[0]
        return Step(Pose(keyframe0.T_world_cam), True, keyframe0.mean_confidence,
                    keyframe0.keyframe_id)

    def _react(self, lost: bool, recovered: bool, timed_out: bool, index: int) -> None:
        """Confidence verdict -> state transitions (and the timeout policy)."""
        state = self.state
        if state is _S.TRACKING and lost:
            self.fire(_E.CONFIDENCE_LOST, index)
        elif state is _S.RELOCALIZING and recovered:
            self.fire(_E.CONFIDENCE_REGAINED, index)
        elif state is _S.RELOCALIZING and timed_out:
            policy_ = self.config.relocalization.timeout_policy
            if policy_ is TimeoutPolicy.STAY:
                self.fire(_E.TIMEOUT_STAY, index)
                return
            # the next map must start from a frame as confident as this map's were, in absolute
            # terms: judged against itself, a frame taken during the loss would pass
            floor = self.monitor.threshold * self.monitor.reference
            if policy_ is TimeoutPolicy.RESET:
                self.drop_map(_R.TIMEOUT, floor=floor)
                self.fire(_E.TIMEOUT_RESET, index)
            else:
                self.drop_map(_R.NEW_MAP, floor=floor)
                self.fire(_E.TIMEOUT_NEW_MAP, index)

    # ------------------------------------------------------------------ maps
    def collect(
        self, index: int, timings: dict[str, float]
    ) -> RebuildOutcome | MappingFailure | None:
        """Take a finished rebuild (installed by the keeper if accepted) and queue its events."""
        outcome = self.keeper.collect(self.backend)
        if isinstance(outcome, MappingFailure):
            self.events.post(*failure_event(outcome))
            return outcome
        if outcome is None:
            return None
        timings["map"] = outcome.map_ms
        for kind, payload in rebuild_events(
            outcome, self.config.rejection.ratio, self._world_change
        ):
            self.events.post(kind, payload)
        if not outcome.accepted:
            return outcome
        if outcome.request.previous is None:
            self._world_change = None  # told (if it was pending): the new world frame is open
        # a new map after a timeout that only the relaxed floor let in (the monitor's reference
        # is still the lost map's: the floor ``_react`` set): the app is told
        relaxed = outcome.request.min_confidence is not None and (
            outcome.candidate_confidence < self.monitor.threshold * self.monitor.reference)
        self.monitor.set_reference(outcome.new_map.keyframes[0].mean_confidence)
        if self.keeper.map is not None:
            for change in self.aligner.after_rebuild(outcome, self.keeper.map):
                self.apply_world(change, index)
        if self.state is _S.MAPPING:
            new_map = outcome.request.cause is RebuildCause.NEW_MAP
            event = _E.NEW_MAP_BUILT if new_map else _E.MAP_BUILT
            self.fire(_E.RELAXED_MAP_BUILT if relaxed else event, index)
        return outcome

    def install_loaded(self, kf_map: KeyframeMap, *, rebuild: bool = False) -> None:
        """Install a saved map and relocalise against it (RELOCALIZING, MAP_LOADED); ``rebuild``:
        extend it even if another preprocessing prepared its keyframes (``MapKeeper.load``)."""
        self.drop_map(_R.MAP_LOADED)
        change, self._world_change = self._world_change, None
        self.keeper.load(kf_map, rebuild=rebuild)
        self.aligner.loaded(kf_map)
        # the backend may have been swapped for another runtime since the map was read
        self.keeper.convert_cache(self.backend.info.dtype, self.backend.info.device)
        self.monitor.set_reference(kf_map.keyframes[0].mean_confidence)
        self.fire(_E.MAP_LOADED, None)
        self.events.post(EventKind.MAP_UPDATED, MapUpdatedEvent.of(kf_map, "loaded"))
        if change is not None:
            self.events.post(EventKind.WORLD_FRAME_CHANGED, WorldFrameChangedEvent(
                _R.MAP_LOADED, change[1], kf_map.generation, None))

    def drop_map(self, why: StateReason, *, floor: float | None = None) -> None:
        """Forget the map (``why`` is told with the next map: a new world frame)."""
        if self.keeper.map is not None:
            self._world_change = (why, self.keeper.generation)
        elif self._world_change is not None:
            self._world_change = (why, self._world_change[1])
        self.keeper.drop(floor=floor)
        self.aligner.reset()
        self.snapshot = replace(self.snapshot, pose=None)

    def fire(self, event: TrackingEvent, index: int | None) -> None:
        """The one place the state changes: the table (``states.NEXT``) chooses the next state
        and its reason from the current state and ``event``; an event that changes nothing in
        this state (``states.UNCHANGED``) sends no state-change event."""
        move = next_state(self.state, event)
        if move is None:
            return
        self.snapshot = replace(self.snapshot, state=move.state, reason=move.reason)
        self.monitor.reset()
        self.events.post(
            EventKind.STATE_CHANGE, StateChangeEvent(move.previous, move.state, move.reason, index)
        )

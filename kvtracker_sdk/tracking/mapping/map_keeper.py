"""``MapKeeper``: the tracker's map over time — when to propose a keyframe, what to evict, starting
rebuilds, and swapping accepted maps in.

It knows nothing of states or events: it answers "should this frame become a keyframe?", starts a
rebuild (inline or on the mapping worker, see ``mapper``), and on ``collect`` installs an accepted
map with one reference assignment (the atomic swap) or notes a rejection. The ``Tracker`` turns
what ``collect`` returns into state changes and events.

The keeper's cycle of mapping passes (idle, building, a candidate waiting, failed with a
backoff) is named in ``rebuild_cycle``: ``phase`` reads it from what the keeper holds, and every
change is checked against that table.

Counters that outlive a map (keyframe ids, generations) never go back, so an id or a generation
seen by an app always names one keyframe or one map.

A candidate that arrives while a rebuild is pending (asynchronous mapping) is **deferred**, not
dropped: it waits in one slot and its rebuild starts as soon as the pending one is collected (the
first frame after the swap, or ``Tracker.wait_for_map``). The keyframe rules count from the last
*proposed* candidate and judge novelty against proposed candidates too, so which frames become
keyframes depends on the frames, not on how fast the mapping worker is — unless a rebuild takes
longer than a whole keyframe interval (an overloaded machine): then a newer candidate replaces the
waiting one, and ``MapStatus.deferred_replaced`` counts it. Rejections are timed from the
candidate's own frame index for the same reason.

A pass that **fails** (the backend raised, or returned non-finite output) is not installed: the
keeper notes it (``MapStatus.failed_passes``, ``last_error``), hands it back to its keyframe id
(no keyframe was made and no event named it), and lets no pass start before ``retry_at_frame``,
which backs off exponentially while failures repeat (``failures.backoff_frames``).

After a map is lost for good (a relocalisation-timeout policy), the next map must start from a
frame that is confident in absolute terms: ``drop(floor=...)`` makes every new bootstrap's keyframe
0 reach that mean confidence (measured against the lost map's reference, not against itself).
After ``FLOOR_RELAXES_AFTER`` such bootstraps in a row were rejected, the floor relaxes once, to
``confidence_threshold`` x the floor: a place where the network is steadily less confident than
where the lost map was made would otherwise never get a map (docs/states.md states the bound).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial

import numpy as np
import torch

from kvtracker_sdk.backends.base import Backend
from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.config import ObjectPreprocessing, TrackerConfig, TrackingMode
from kvtracker_sdk.errors import MappingFailedError, MapPreprocessingError, StateError
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.tracking.core.gauge import keyframe_corrections
from kvtracker_sdk.tracking.core.model_input import PreparedFrame
from kvtracker_sdk.tracking.mapping import keyframes as policy
from kvtracker_sdk.tracking.mapping.failures import MappingFailure, backoff_frames, mapping_error
from kvtracker_sdk.tracking.mapping.map_builder import (
    KeyframeCandidate,
    RebuildCause,
    RebuildOutcome,
    RebuildRequest,
)
from kvtracker_sdk.tracking.mapping.map_insertion import rebuild_or_insert
from kvtracker_sdk.tracking.mapping.mapper import Mapper
from kvtracker_sdk.tracking.mapping.rebuild_cycle import RebuildEvent, RebuildPhase, check_move
from kvtracker_sdk.tracking.object.object_model import ObjectModelCache
from kvtracker_sdk.tracking.world.world_alignment import WorldChange, transform_map
from kvtracker_sdk.types import MapStatus
from kvtracker_sdk.world import MapWorld, ScaleSource

__all__ = ["FLOOR_RELAXES_AFTER", "MapKeeper"]

_log = get_logger(__name__)
_NEVER = -(10**12)
# Rejected bootstraps in a row (after a timeout) before the confidence floor relaxes. Small: each
# costs `rejection.retry_after_frames` frames without poses; a few so that one unlucky frame
# right after the timeout does not relax the floor at once.
FLOOR_RELAXES_AFTER = 3


@dataclass(frozen=True)
class _Proposal:
    """A frame proposed as a keyframe, with the pose it was judged at."""

    frame: PreparedFrame
    index: int
    T_world_cam: np.ndarray


class MapKeeper:
    """Holds the current ``KeyframeMap`` and runs its rebuilds for one tracker."""

    def __init__(self, config: TrackerConfig, *, preprocessing: str) -> None:
        self._config = config
        self._preprocessing = preprocessing  # what prepares frames for new maps (the family's)
        self._rebuild_foreign = False  # the loaded map may be extended across preprocessings
        self._mapper: Mapper[RebuildOutcome] = Mapper(asynchronous=config.threading.async_mapping)
        self._budget = policy.KeyframeBudget(config.keyframing.budget)
        self.map: KeyframeMap | None = None
        self.objects = ObjectModelCache()  # the object of the current map (object mode)
        self.generation = 0  # of the latest installed map; 0 before the first
        self._next_keyframe_id = 0
        self._deferred_replaced = 0  # waiting candidates replaced by newer ones (overload)
        self._failed_passes = 0
        self._last_error: MappingFailedError | None = None
        self._floor: float | None = None  # absolute confidence a new map's keyframe 0 must reach
        # rebuilds started / taken (or discarded), in order: lets a waiter know when "its" are done
        self._started = self._taken = 0
        self._clear_counters()

    def _clear_counters(self) -> None:
        self._last_accepted_frame = _NEVER  # frame of the last accepted keyframe (this session)
        self._last_proposed_frame = _NEVER  # frame of the last candidate proposed (this session)
        self._retry_frame = _NEVER  # no candidate before this frame (after a rejection)
        self._centre: tuple[int, np.ndarray] | None = None  # (generation, object centre)
        # candidates proposed but not in the installed map: the pending one, then the waiting one
        self._in_flight: tuple[_Proposal, ...] = ()
        self._waiting: _Proposal | None = None
        self._request: RebuildRequest | None = None  # of the pending rebuild
        # world transforms applied since the pending rebuild started (its map is in the old world)
        self._pending_world: Sim3 | None = None
        self._consecutive_failures = 0
        self._floor_rejections = 0  # bootstraps in a row below the floor (relaxes it)
        self._count_from_next = False  # a loaded map: the interval counts from its first frame

    @property
    def phase(self) -> RebuildPhase:
        """Where the rebuild cycle is (``rebuild_cycle``), read from what the keeper holds."""
        if self._mapper.pending:
            if self._waiting is not None:
                return RebuildPhase.CANDIDATE_WAITING
            return RebuildPhase.BUILDING
        return RebuildPhase.FAILED if self._consecutive_failures > 0 else RebuildPhase.IDLE

    @property
    def rebuilding(self) -> bool:
        """A rebuild was started and its result not installed (or rejected) yet."""
        return self._mapper.pending

    def status(self) -> MapStatus:
        kf_map, failing = self.map, self._consecutive_failures > 0
        # the generation never goes back, also without a map (after reset)
        return MapStatus(
            num_keyframes=0 if kf_map is None else kf_map.num_keyframes,
            cache_bytes=0 if kf_map is None else kf_map.cache.nbytes,
            generation=self.generation if kf_map is None else kf_map.generation,
            rebuilding=self._mapper.pending,
            keyframe_ids=() if kf_map is None else kf_map.keyframe_ids,
            keyframe_waiting=self._waiting is not None,
            deferred_replaced=self._deferred_replaced,
            failed_passes=self._failed_passes,
            last_error=self._last_error,
            retry_at_frame=self._retry_frame if failing else None,
            world=MapWorld() if kf_map is None else kf_map.world,
        )

    # ------------------------------------------------------------------ world transforms
    def transform_world(self, change: WorldChange) -> KeyframeMap:
        """Re-express the map in a new world (``change.transform``: new <- old) as a new
        generation; a rebuild in flight gets the same transform when it is collected, and the
        candidates' poses move with it. Returns the new map."""
        kf_map = self.map
        if kf_map is None:
            raise StateError("no map to transform")
        W = change.transform
        self.generation += 1
        self.map = transform_map(kf_map, W, generation=self.generation, world=change.world)
        if self._mapper.pending:
            self._pending_world = W if self._pending_world is None else W @ self._pending_world
        self._in_flight = tuple(replace(p, T_world_cam=W.apply_to_pose(p.T_world_cam))
                                for p in self._in_flight)
        if self._waiting is not None:
            self._waiting = replace(
                self._waiting, T_world_cam=W.apply_to_pose(self._waiting.T_world_cam))
        return self.map

    def _into_current_world(self, outcome: RebuildOutcome) -> RebuildOutcome:
        """A rebuild started before a world transform: its map moved into the current world (a
        newer generation than the transformed map's, corrections against it)."""
        W, self._pending_world = self._pending_world, None
        current = self.map
        if W is None or not outcome.accepted or current is None:
            return outcome
        world = current.world
        depth = ScaleSource.DEPTH
        if outcome.new_map.world.scale_source is depth and world.scale_source is depth:
            world = outcome.new_map.world  # anchored to depth again: its fit's uncertainty
        moved = transform_map(outcome.new_map, W, generation=self.generation + 1, world=world)
        return replace(outcome, new_map=moved,
                       correction=keyframe_corrections(current.keyframes, moved.keyframes))

    # ------------------------------------------------------------------ whole maps
    def drop(self, *, floor: float | None = None) -> None:
        """Forget the map and any rebuild in flight (its result will be ignored). ``floor``: the
        absolute mean confidence the next map's keyframe 0 must reach (None: any frame)."""
        before = self.phase
        self._mapper.discard()
        self._taken = self._started
        self._pending_world = None
        self.map = None
        self._rebuild_foreign = False
        self._floor = floor
        self._clear_counters()
        check_move(before, RebuildEvent.DROP, self.phase)

    def convert_cache(self, dtype: str, device: str, *, dequantize: bool = False) -> None:
        """Re-express the map's K/V in another backend's dtype and device (a backend swap between
        runtimes or precisions of the same model: same function, different storage). A quantised
        cache stays quantised unless ``dequantize`` (a backend that cannot read one)."""
        kf_map = self.map
        target_dtype, target_device = getattr(torch, dtype), torch.device(device)
        if kf_map is not None and dequantize and kf_map.cache.quantized:
            self.map = replace(kf_map, cache=kf_map.cache.to(device=target_device, storage=dtype))
        elif kf_map is not None and (kf_map.cache.dtype, kf_map.cache.device) != (
            target_dtype,
            target_device,
        ):
            self.map = replace(
                kf_map, cache=kf_map.cache.to(dtype=target_dtype, device=target_device)
            )

    def load(self, kf_map: KeyframeMap, *, rebuild: bool = False) -> None:
        """Install a map built elsewhere (a saved map); ids and generations continue after it.

        A map whose keyframes another preprocessing prepared is tracked against but not extended
        unless ``rebuild`` (its new keyframes are then prepared its way, by the tracker)."""
        self.drop()
        self.map = kf_map
        self._rebuild_foreign = rebuild
        self.generation = max(self.generation, kf_map.generation)
        self._next_keyframe_id = max(self._next_keyframe_id, max(kf_map.keyframe_ids) + 1)
        self._count_from_next = True

    def may_start(self, index: int) -> bool:
        """Whether a pass may start at frame ``index`` (not during a failure's backoff or after a
        rejection's wait)."""
        return index >= self._retry_frame

    # ------------------------------------------------------------------ waiting (no tracker lock)
    def settle_target(self) -> int:
        """A ticket for "the rebuilds pending or waiting now": pass it to ``settled``."""
        return self._started + (1 if self._waiting is not None else 0)

    def settled(self, target: int) -> bool:
        """Whether the rebuilds of ``target`` (from ``settle_target``) were taken, or nothing is
        pending or waiting any more (a waiting candidate may be dropped without a rebuild)."""
        return self._taken >= target or not (self._mapper.pending or self._waiting is not None)

    def wait(self, timeout: float | None) -> bool:
        """Wait until the pending rebuild has finished (not installed: ``collect`` does that).
        Called without the tracker's lock, so frames keep flowing meanwhile."""
        return self._mapper.wait(timeout)

    # ------------------------------------------------------------------ keyframes
    @property
    def extendable(self) -> bool:
        """Whether keyframes may be added to the current map: it was made by this tracker's
        preprocessing, or loading it asked to rebuild it anyway."""
        kf_map = self.map
        if kf_map is None:
            return False
        return kf_map.preprocessing == self._preprocessing or self._rebuild_foreign

    def wants_keyframe(self, T_world_cam: np.ndarray, index: int) -> bool:
        """Whether the confidently tracked frame ``index`` at ``T_world_cam`` should be proposed.

        Judged against the installed map *and* the candidates already proposed (pending or
        waiting), so the answer does not depend on whether their rebuilds have finished yet.
        """
        kf_map = self.map
        if kf_map is None or index < self._retry_frame:
            return False
        if not self.extendable:
            return False  # a map from another preprocessing is tracked against, never extended
        if self._count_from_next:  # the first frame tracked against a loaded map starts the count
            self._count_from_next = False
            self._last_proposed_frame = index
            return False
        capacity = self._budget.capacity(kf_map.cache.bytes_per_keyframe())
        if capacity is not None and capacity < 2:
            return False  # the budget holds keyframe 0 only
        keyframing = self._config.keyframing
        if self._config.mode is TrackingMode.SCENE:
            return policy.interval_elapsed(
                index, self._last_proposed_frame, keyframing.interval_frames
            )
        if self._centre is None or self._centre[0] != kf_map.generation:
            model = self.objects.get(kf_map)  # shared with the region propagation
            centre = model.centre if model is not None else policy.object_centre(kf_map.keyframes)
            self._centre = (kf_map.generation, centre)
        proposed = [p.T_world_cam for p in self._proposals()]
        poses = np.concatenate([kf_map.poses(), np.asarray(proposed).reshape(-1, 4, 4)])
        return policy.novel_object_view(
            keyframing.object_rule, T_world_cam, poses, self._centre[1], keyframing.view_angle_deg
        )

    def _proposals(self) -> tuple[_Proposal, ...]:
        return self._in_flight + ((self._waiting,) if self._waiting is not None else ())

    def propose(
        self, backend: Backend, frame: PreparedFrame, index: int, T_world_cam: np.ndarray
    ) -> int | None:
        """Propose the frame as a keyframe: its rebuild starts now (returns the candidate's id),
        or, while another rebuild is pending, it waits for that one (returns None).

        MapPreprocessingError if the map's keyframes were prepared by another preprocessing and
        loading it did not ask to rebuild it (``wants_keyframe`` is then always False)."""
        kf_map = self.map
        if kf_map is not None and not self.extendable:
            raise MapPreprocessingError(
                f"the map's keyframes were prepared by {kf_map.preprocessing!r}, new keyframes by "
                f"{self._preprocessing!r}: load the map with rebuild=True to extend it anyway"
            )
        proposal = _Proposal(frame, index, np.asarray(T_world_cam, dtype=np.float64))
        self._last_proposed_frame = index
        before = self.phase
        if before in (RebuildPhase.IDLE, RebuildPhase.FAILED):
            return self._start_keyframe(backend, proposal)
        event = RebuildEvent.DEFER
        if self._waiting is not None:
            event = RebuildEvent.REPLACE
            self._deferred_replaced += 1
            _log.warning("keyframe candidate replaced while waiting for a slow rebuild",
                         replaced_frame=self._waiting.index, frame_index=index)
        self._waiting = proposal
        check_move(before, event, self.phase)
        return None

    def start_bootstrap(
        self, backend: Backend, frame: PreparedFrame, index: int, cause: RebuildCause
    ) -> None:
        """Start the first map (or a new one): ``frame`` becomes keyframe 0."""
        self._start(backend, None, (), frame, index, cause)

    def _start_keyframe(self, backend: Backend, proposal: _Proposal) -> int:
        """Start a rebuild adding ``proposal`` (evicting to fit the budget); the candidate's id."""
        kf_map = self.map
        if kf_map is None:
            raise StateError("no map to add a keyframe to")
        evicted = self._budget.select_evictions(kf_map.keyframes, kf_map.cache.bytes_per_keyframe())
        keep = tuple(kf for kf in kf_map.keyframes if kf.keyframe_id not in evicted)
        self._in_flight = (proposal,)
        return self._start(backend, kf_map, keep, proposal.frame, proposal.index,
                           RebuildCause.KEYFRAME, evicted)

    def _bootstrap_floor(self) -> float | None:
        """The mean confidence a new map's keyframe 0 must reach now (None: any frame): the lost
        map's floor, relaxed once by ``confidence_threshold`` after ``FLOOR_RELAXES_AFTER``
        rejections in a row. Never lower: frames of a deep loss stay below it."""
        if self._floor is None or self._floor_rejections < FLOOR_RELAXES_AFTER:
            return self._floor
        return self._floor * self._config.relocalization.confidence_threshold

    def _start(
        self,
        backend: Backend,
        previous: KeyframeMap | None,
        keep: tuple,
        frame: PreparedFrame,
        index: int,
        cause: RebuildCause,
        evicted: tuple[int, ...] = (),
    ) -> int:
        before = self.phase
        candidate = KeyframeCandidate(
            self._next_keyframe_id, index, frame.timestamp, frame.image, frame.mask,
            frame.preprocessing, frame.depth,
        )
        self._next_keyframe_id += 1
        self._last_proposed_frame = max(self._last_proposed_frame, index)  # bootstraps count too
        floor = self._bootstrap_floor() if previous is None else None
        # a new world takes its scale from a depth frame if it has one; a world metric by depth
        # keeps taking it from the sensor (no drift through rebuilds)
        anchor = previous is None or previous.world.scale_source is ScaleSource.DEPTH
        request = RebuildRequest(
            previous, keep, evicted, candidate, cause, self.generation + 1, min_confidence=floor,
            anchor_to_depth=anchor,
        )
        self._request = request
        self._started += 1
        config = self._config
        # masked object frames are black off the object: their tokens there may be dropped
        object_masked = (
            config.mode == TrackingMode.OBJECT
            and config.object.preprocessing == ObjectPreprocessing.MASK
        )
        storage = config.cache_dtype
        self._mapper.submit(
            partial(
                rebuild_or_insert,
                backend,
                request,
                rejection=config.rejection,
                align_gauge=config.debug.gauge_alignment,
                compaction=config.compaction,
                object_masked=object_masked,
                cache_storage=None if storage == "backend" else storage,
            )
        )
        check_move(before, RebuildEvent.START, self.phase)
        return candidate.keyframe_id

    def collect(
        self, backend: Backend, *, timeout: float | None = 0.0
    ) -> RebuildOutcome | MappingFailure | None:
        """Install a finished rebuild if accepted (or note its rejection or failure), then start
        the waiting candidate's rebuild, if any, on ``backend``.

        Returns the outcome (a ``MappingFailure`` if the pass failed: it never raises), or None
        when no rebuild finished within ``timeout`` seconds.
        """
        request, before = self._request, self.phase
        try:
            outcome = self._mapper.take(timeout=timeout)
        except Exception as exc:  # any backend failure: the frame loop must go on
            assert request is not None  # a pending job always has its request
            failure = self._failed(backend, request, exc)
            check_move(before, RebuildEvent.FAIL, self.phase)
            return failure
        if outcome is None:
            return None
        outcome = self._into_current_world(outcome)
        self._taken, self._request = self._started, None
        self._in_flight, self._consecutive_failures, self._last_error = (), 0, None
        candidate_frame = outcome.request.candidate.frame_index
        if outcome.accepted:
            self.map = outcome.new_map  # the atomic swap: readers see the old map or the new one
            self.generation = outcome.new_map.generation
            self._last_accepted_frame = candidate_frame
            self._floor = None
        else:
            # timed from the candidate's frame (not from when the worker finished): deterministic
            self._retry_frame = candidate_frame + self._config.rejection.retry_after_frames
            if outcome.request.min_confidence is not None:  # a bootstrap below the floor
                self._floor_rejections += 1
            self._last_proposed_frame = self._last_accepted_frame
        self._start_waiting(backend)
        check_move(before, RebuildEvent.ACCEPT if outcome.accepted else RebuildEvent.REJECT,
                   self.phase)
        return outcome

    def _failed(
        self, backend: Backend, request: RebuildRequest, exc: Exception
    ) -> MappingFailure:
        """Note a failed pass: the map stays, the candidate never existed, retries back off."""
        self._taken, self._request = self._started, None
        self._pending_world = None
        error = mapping_error(exc, request)
        self._failed_passes += 1
        self._consecutive_failures += 1
        self._last_error = error
        candidate = request.candidate
        if self._next_keyframe_id == candidate.keyframe_id + 1:
            self._next_keyframe_id = candidate.keyframe_id  # no event named it: not burnt
        retry_at = candidate.frame_index + backoff_frames(self._consecutive_failures)
        self._retry_frame = max(self._retry_frame, retry_at)
        # the next frame past the backoff may propose again
        self._in_flight, self._last_proposed_frame = (), self._last_accepted_frame
        _log.warning("mapping pass failed", cause=request.cause.value, frame_index=candidate.frame_index,
                     error=str(error), retry_at_frame=retry_at)
        self._start_waiting(backend)
        return MappingFailure(request, error, self._consecutive_failures, retry_at)

    def _start_waiting(self, backend: Backend) -> None:
        """Start the waiting candidate's rebuild, unless it fell into a wait (then drop it)."""
        waiting, self._waiting = self._waiting, None
        if waiting is not None and self.map is not None and waiting.index >= self._retry_frame:
            self._start_keyframe(backend, waiting)

    def close(self) -> None:
        self._mapper.close()

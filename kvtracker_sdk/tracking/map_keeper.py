"""``MapKeeper``: the tracker's map over time — when to propose a keyframe, what to evict, starting
rebuilds, and swapping accepted maps in.

It knows nothing of states or events: it answers "should this frame become a keyframe?", starts a
rebuild (inline or on the mapping worker, see ``mapper``), and on ``collect`` installs an accepted
map with one reference assignment (the atomic swap) or notes a rejection. The ``Tracker`` turns
what ``collect`` returns into state changes and events.

Counters that outlive a map (keyframe ids, generations) never go back, so an id or a generation
seen by an app always names one keyframe or one map.
"""

from __future__ import annotations

from dataclasses import replace
from functools import partial

import numpy as np
import torch

from kvtracker_sdk.backends.base import Backend
from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.config import TrackerConfig, TrackingMode
from kvtracker_sdk.errors import StateError
from kvtracker_sdk.tracking import keyframes as policy
from kvtracker_sdk.tracking.frame_input import PreparedFrame
from kvtracker_sdk.tracking.map_builder import (
    KeyframeCandidate,
    RebuildOutcome,
    RebuildRequest,
    build_map,
)
from kvtracker_sdk.tracking.mapper import Mapper
from kvtracker_sdk.types import MapStatus

__all__ = ["MapKeeper"]

_NEVER = -(10**12)


class MapKeeper:
    """Holds the current ``KeyframeMap`` and runs its rebuilds for one tracker."""

    def __init__(self, config: TrackerConfig) -> None:
        self._config = config
        self._mapper: Mapper[RebuildOutcome] = Mapper(asynchronous=config.threading.async_mapping)
        self._budget = policy.KeyframeBudget(config.keyframing.budget)
        self.map: KeyframeMap | None = None
        self.generation = 0  # of the latest installed map; 0 before the first
        self._next_keyframe_id = 0
        self._clear_counters()

    def _clear_counters(self) -> None:
        self._last_keyframe_frame = _NEVER  # frame of the last accepted keyframe (this session)
        self._retry_frame = _NEVER  # no candidate before this frame (after a rejection)
        self._centre: tuple[int, np.ndarray] | None = None  # (generation, object centre)

    @property
    def rebuilding(self) -> bool:
        """A rebuild was started and its result not installed (or rejected) yet."""
        return self._mapper.pending

    def status(self) -> MapStatus:
        kf_map, rebuilding = self.map, self._mapper.pending
        if kf_map is None:
            return MapStatus(0, 0, 0, rebuilding)
        return MapStatus(
            kf_map.num_keyframes,
            kf_map.cache.nbytes,
            kf_map.generation,
            rebuilding,
            kf_map.keyframe_ids,
        )

    # ------------------------------------------------------------------ whole maps
    def drop(self) -> None:
        """Forget the map and any rebuild in flight (its result will be ignored)."""
        self._mapper.discard()
        self.map = None
        self._clear_counters()

    def convert_cache(self, dtype: str, device: str) -> None:
        """Re-express the map's K/V in another backend's dtype and device (a backend swap between
        runtimes or precisions of the same model: same function, different storage)."""
        kf_map = self.map
        target_dtype, target_device = getattr(torch, dtype), torch.device(device)
        if kf_map is not None and (kf_map.cache.dtype, kf_map.cache.device) != (
            target_dtype,
            target_device,
        ):
            self.map = replace(
                kf_map, cache=kf_map.cache.to(dtype=target_dtype, device=target_device)
            )

    def load(self, kf_map: KeyframeMap) -> None:
        """Install a map built elsewhere (a saved map); ids and generations continue after it."""
        self.drop()
        self.map = kf_map
        self.generation = max(self.generation, kf_map.generation)
        self._next_keyframe_id = max(self._next_keyframe_id, max(kf_map.keyframe_ids) + 1)

    # ------------------------------------------------------------------ keyframes
    def wants_keyframe(self, T_world_cam: np.ndarray, index: int) -> bool:
        """Whether the confidently tracked frame ``index`` at ``T_world_cam`` should be proposed."""
        kf_map = self.map
        if kf_map is None or self._mapper.pending or index < self._retry_frame:
            return False
        capacity = self._budget.capacity(kf_map.cache.bytes_per_keyframe())
        if capacity is not None and capacity < 2:
            return False  # the budget holds keyframe 0 only
        keyframing = self._config.keyframing
        if self._config.mode is TrackingMode.SCENE:
            return policy.interval_elapsed(
                index, self._last_keyframe_frame, keyframing.interval_frames
            )
        if self._centre is None or self._centre[0] != kf_map.generation:
            self._centre = (kf_map.generation, policy.object_centre(kf_map.keyframes))
        return policy.novel_view(
            T_world_cam, kf_map.poses(), self._centre[1], keyframing.view_angle_deg
        )

    def start_bootstrap(
        self, backend: Backend, frame: PreparedFrame, index: int, cause: str
    ) -> None:
        """Start the first map (or a new one): ``frame`` becomes keyframe 0."""
        self._start(backend, None, (), frame, index, cause)

    def start_keyframe(self, backend: Backend, frame: PreparedFrame, index: int) -> int:
        """Start a rebuild adding ``frame`` (evicting to fit the budget); the candidate's id."""
        kf_map = self.map
        if kf_map is None:
            raise StateError("no map to add a keyframe to")
        evicted = self._budget.select_evictions(kf_map.keyframes, kf_map.cache.bytes_per_keyframe())
        keep = tuple(kf for kf in kf_map.keyframes if kf.keyframe_id not in evicted)
        return self._start(backend, kf_map, keep, frame, index, "keyframe", evicted)

    def _start(
        self,
        backend: Backend,
        previous: KeyframeMap | None,
        keep: tuple,
        frame: PreparedFrame,
        index: int,
        cause: str,
        evicted: tuple[int, ...] = (),
    ) -> int:
        candidate = KeyframeCandidate(
            self._next_keyframe_id, index, frame.timestamp, frame.image, frame.mask
        )
        self._next_keyframe_id += 1
        request = RebuildRequest(previous, keep, evicted, candidate, cause, self.generation + 1)
        self._mapper.submit(
            partial(
                build_map,
                backend,
                request,
                rejection=self._config.rejection,
                align_gauge=self._config.debug.gauge_alignment,
            )
        )
        return candidate.keyframe_id

    def collect(self, index: int, *, timeout: float | None = 0.0) -> RebuildOutcome | None:
        """Install a finished rebuild if accepted (or note its rejection at frame ``index``).

        Returns the outcome, or None when no rebuild finished within ``timeout`` seconds.
        """
        outcome = self._mapper.take(timeout=timeout)
        if outcome is None:
            return None
        if outcome.accepted:
            self.map = outcome.new_map  # the atomic swap: readers see the old map or the new one
            self.generation = outcome.new_map.generation
            self._last_keyframe_frame = outcome.request.candidate.frame_index
        else:
            self._retry_frame = index + self._config.rejection.retry_after_frames
        return outcome

    def close(self) -> None:
        self._mapper.close()

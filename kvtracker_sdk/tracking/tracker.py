"""``Tracker``: the SDK's facade — frames in, poses out — and the only caller of ``transition``.

Per frame: validate and resize (``frame_input``), track against the current map's KV cache, map
the raw pose into the world frame through the map's gauge, judge confidence (``quality``), move
through the state table (``states``), and maybe propose a keyframe (``keyframes``), which rebuilds
the map inline or on the mapping worker (``mapper`` / ``map_builder``). Events are queued while the
tracker's lock is held and delivered after it is released, on the calling thread (``events``).
Maps are saved, loaded and exported through ``persistence``.

Thread safety: every public method may be called from any thread. ``push_frame`` calls are
serialised; ``get_pose``, ``state``, ``reason``, ``map_status`` and ``keyframe_map`` read single
immutable snapshots and never block on a frame or a rebuild.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from kvtracker_sdk.backends.base import Backend
from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.config import TimeoutPolicy, TrackerConfig
from kvtracker_sdk.errors import BackendMismatchError, MissingDependencyError, StateError
from kvtracker_sdk.io.map_file import MapInfo
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.tracking import persistence
from kvtracker_sdk.tracking.events import (
    Callback,
    EventBus,
    EventKind,
    KeyframeEvent,
    KeyframeRejectedEvent,
    MapUpdatedEvent,
    StateChangeEvent,
    Subscription,
)
from kvtracker_sdk.tracking.frame_input import FramePreparer, PreparedFrame
from kvtracker_sdk.tracking.map_builder import RebuildOutcome
from kvtracker_sdk.tracking.map_keeper import MapKeeper
from kvtracker_sdk.tracking.persistence import ConfigOverride, PathLike
from kvtracker_sdk.tracking.quality import ConfidenceMonitor, frame_confidence
from kvtracker_sdk.tracking.states import transition
from kvtracker_sdk.types import FrameResult, MapStatus, Pose, StateReason, TrackingState

__all__ = ["Tracker"]

_log = get_logger(__name__)
_S, _R = TrackingState, StateReason


def _ms(since: float) -> float:
    return (time.perf_counter() - since) * 1e3


class Tracker:
    """Tracks a camera (scene mode) or an object (object mode) from RGB frames.

    ``Tracker(config, backend)``: ``config`` is a ``TrackerConfig`` (or a dict of its fields, or
    None for defaults); ``backend`` implements ``kvtracker_sdk.backends.base.Backend``. The tracker
    does not close a backend it was given; it closes one it created (``from_pretrained``).
    Callbacks (``on_*``) run on the thread that called the method causing them (see ``events``).
    """

    def __init__(self, config: TrackerConfig | Mapping[str, Any] | None, backend: Backend) -> None:
        cfg = config if isinstance(config, TrackerConfig) else TrackerConfig.from_dict(config or {})
        self._preparer = FramePreparer(
            cfg, patch_size=backend.info.patch_size, family=backend.info.family
        )
        cfg = self._preparer.config  # an unset resolution becomes the family's default
        self._config = cfg
        self._backend = backend
        self._owns_backend = False
        self._events = EventBus()
        self._keeper = MapKeeper(cfg, preprocessing=self._preparer.preprocessing.name)
        self._monitor = ConfidenceMonitor.from_config(cfg.relocalization)
        self._lock = threading.RLock()
        self._status: tuple[TrackingState, StateReason] = (_S.INIT, _R.NONE)
        self._input_size: tuple[int, int] | None = None  # of the session's frames
        self._frames = 0  # frame indices are never reused by one tracker
        self._last_pose: Pose | None = None
        self._closed = False

    @classmethod
    def from_pretrained(cls, weights: str | Path, **config: Any) -> Tracker:
        """A tracker over the PyTorch backend loaded from ``weights`` (file, folder or hub id);
        ``config`` holds ``TrackerConfig`` fields (validated before the weights load)."""
        cfg = TrackerConfig.from_dict(config)
        try:
            from kvtracker_sdk.backends.torch_backend import TorchBackend
        except ImportError as exc:
            raise MissingDependencyError(f"the PyTorch backend cannot be imported: {exc}") from exc
        tracker = cls(cfg, TorchBackend.from_pretrained(weights))
        tracker._owns_backend = True
        return tracker

    @classmethod
    def from_map(
        cls, path: PathLike, backend: Backend, config: ConfigOverride = None, *,
        rebuild: bool = False,
    ) -> Tracker:
        """A tracker relocalising against the map saved at ``path`` by ``backend``'s model.
        ``config``: None keeps the map's saved one; a dict changes some of its fields.

        A map whose keyframes another preprocessing prepared (saved before the SDK followed the
        official pipelines: header without ``preprocessing``) is tracked against with frames
        prepared its way, and not extended; ``rebuild=True`` lets new keyframes extend it (also
        prepared its way). Extending it otherwise raises ``MapPreprocessingError``."""
        loaded = persistence.load_tracker_map(path, backend.info, config)
        tracker = cls(loaded.config, backend)
        tracker._install_loaded_map(loaded.keyframe_map, rebuild=rebuild)
        return tracker

    # ------------------------------------------------------------------ read-only views
    @property
    def config(self) -> TrackerConfig:
        return self._config

    @property
    def backend(self) -> Backend:
        return self._backend

    @property
    def state(self) -> TrackingState:
        return self._status[0]

    @property
    def reason(self) -> StateReason:
        return self._status[1]

    @property
    def keyframe_map(self) -> KeyframeMap | None:
        """The current map (immutable; replaced as a whole on every accepted rebuild)."""
        return self._keeper.map

    @property
    def map_status(self) -> MapStatus:
        return self._keeper.status()

    def get_pose(self) -> Pose | None:
        """The last valid ``T_world_cam`` (None before the first, and after a reset)."""
        return self._last_pose

    # ------------------------------------------------------------------ events
    def on_keyframe(self, callback: Callback) -> Subscription:
        return self._events.register(EventKind.KEYFRAME, callback)

    def on_keyframe_rejected(self, callback: Callback) -> Subscription:
        return self._events.register(EventKind.KEYFRAME_REJECTED, callback)

    def on_state_change(self, callback: Callback) -> Subscription:
        return self._events.register(EventKind.STATE_CHANGE, callback)

    def on_map_updated(self, callback: Callback) -> Subscription:
        return self._events.register(EventKind.MAP_UPDATED, callback)

    def unregister(self, handle: Subscription | Callback) -> bool:
        """Remove a subscription (or every registration of a callback)."""
        return self._events.unregister(handle)

    # ------------------------------------------------------------------ session control
    def initialize(self, map: PathLike | None = None, *, rebuild: bool = False) -> None:
        """Start a fresh session: without ``map``, no map and state INIT; with ``map``, relocalise
        against the map saved at that path under this tracker's configuration (its mode and
        resolution must be the map's; ``rebuild`` as in ``from_map``). A load that fails raises
        and changes nothing."""
        if map is None:
            self.reset()
            return
        loaded = persistence.load_tracker_map(map, self._backend.info, self._config)
        self._install_loaded_map(loaded.keyframe_map, rebuild=rebuild)

    def reset(self) -> None:
        """Drop the map (a pending rebuild is discarded) and return to INIT with reason RESET."""
        with self._call():
            self._drop_map()
            self._input_size = None
            if self.state is not _S.INIT:
                self._change(_S.INIT, _R.RESET, None)

    def _install_loaded_map(self, kf_map: KeyframeMap, *, rebuild: bool = False) -> None:
        """Persistence seam: install a saved map and relocalise against it (RELOCALIZING,
        MAP_LOADED). The caller has checked the map's model fingerprint."""
        with self._call():
            if kf_map.cache.layout != self._backend.info.layout:
                raise BackendMismatchError(
                    f"map cache layout {kf_map.cache.layout} != backend {self._backend.info.layout}"
                )
            self._drop_map()
            self._input_size = None
            self._keeper.load(kf_map, rebuild=rebuild)
            if not self._keeper.extendable:
                _log.warning(
                    "map made by another preprocessing: tracking only, no new keyframes",
                    map_preprocessing=kf_map.preprocessing,
                    preprocessing=self._preparer.preprocessing.name,
                    hint="load it with rebuild=True to extend it",
                )
            # the backend may have been swapped for another runtime since the map was read
            self._keeper.convert_cache(self._backend.info.dtype, self._backend.info.device)
            self._monitor.set_reference(kf_map.keyframes[0].mean_confidence)
            self._change(_S.RELOCALIZING, _R.MAP_LOADED, None)
            self._events.post(EventKind.MAP_UPDATED, MapUpdatedEvent.of(kf_map, "loaded"))

    def set_backend(self, backend: Backend) -> Backend:
        """Swap backends between frames (e.g. torch -> onnx); returns the previous one, unclosed.

        The two must compute the same function: equal ``info.fingerprint`` and ``info.layout``.
        A pending rebuild is waited for, and the map's cache is converted if the new backend
        computes in another dtype or on another device.
        """
        old, new = self._backend.info, backend.info
        if old.fingerprint != new.fingerprint or old.layout != new.layout:
            raise BackendMismatchError(
                f"cannot swap {old.backend}/{old.model} (fingerprint {old.fingerprint}, layout "
                f"{old.layout}) for {new.backend}/{new.model} (fingerprint {new.fingerprint}, "
                f"layout {new.layout})"
            )
        with self._call():
            self._settle(timeout=None)  # rebuilds made by the old backend
            self._keeper.convert_cache(new.dtype, new.device)
            previous, self._backend, self._owns_backend = self._backend, backend, False
        return previous

    def save_map(self, path: PathLike) -> MapInfo:
        """Save the map (after a pending rebuild) atomically: ``path`` keeps its old content or
        holds the whole new map. StateError without a map; MapIOError if it cannot write."""
        kf_map = self._settled_map()
        return persistence.save_tracker_map(path, kf_map, self._backend.info, self._config)

    def export_point_cloud(self, path: PathLike, **options: Any) -> int:
        """The map's point cloud as PLY; ``options`` and return: ``persistence``'s."""
        return persistence.export_point_cloud(self._settled_map(), path, **options)

    def export_trajectory(self, path: PathLike) -> int:
        """The keyframes' world poses as a TUM trajectory; returns the number of poses."""
        return persistence.export_trajectory(self._settled_map(), path)

    def wait_for_map(self, timeout: float | None = None) -> bool:
        """Wait for pending rebuilds (and a keyframe waiting for one) and install them; True when
        none is pending any more, False if ``timeout`` seconds passed first."""
        with self._call():
            return self._settle(timeout)

    def close(self) -> None:
        """Stop the mapping worker (and close a backend this tracker created). Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._keeper.close()
            if self._owns_backend:
                self._backend.close()

    def __enter__(self) -> Tracker:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # ------------------------------------------------------------------ the frame loop
    def push_frame(
        self, image: np.ndarray, timestamp: float | None = None, mask: np.ndarray | None = None,
        bbox: Any = None,
    ) -> FrameResult:
        """Track one RGB frame [H, W, 3] (uint8, or float in [0, 1]).

        ``mask`` (bool/int [H, W]) or ``bbox`` (x0, y0, x1, y1) select the object (required in
        object mode). The result's ``pose`` is None without a map (INIT, MAPPING); ``pose_valid``
        is False while relocalising or for a low-confidence frame. ``keyframe_id`` is set when the
        frame became a keyframe in this call (synchronous mapping; with asynchronous mapping the
        ``on_keyframe`` event reports it later). Bad input raises an ``InputError`` subclass
        before anything changes.
        """
        start = time.perf_counter()
        with self._call():
            kf_map = self._keeper.map
            frame = self._preparer.prepare(
                image, timestamp=timestamp, mask=mask, bbox=bbox,
                session_input_size=self._input_size,
                map_resolution=None if kf_map is None else kf_map.resolution,
                map_preprocessing=None if kf_map is None else kf_map.preprocessing,
            )
            timings = {"preprocess": _ms(start)}
            index, self._frames = self._frames, self._frames + 1
            self._input_size = frame.input_size
            self._collect(index, timings)
            pose, valid, confidence, keyframe_id = self._process(frame, index, timings)
            if valid:
                self._last_pose = pose
            timings["total"] = _ms(start)
            result = FrameResult(
                index, frame.timestamp, self.state, self.reason, pose, valid, confidence,
                keyframe_id, self.map_status.generation, timings,
                {"rebuilding": self._keeper.rebuilding},
            )
        _log.debug("frame", frame_index=index, state=result.state.value, pose_valid=valid,
                   confidence=confidence, **{f"{k}_ms": round(v, 3) for k, v in timings.items()})
        return result

    def _process(
        self, frame: PreparedFrame, index: int, timings: dict[str, float]
    ) -> tuple[Pose | None, bool, float | None, int | None]:
        """(pose, pose_valid, confidence, keyframe_id) of one validated frame."""
        kf_map = self._keeper.map
        if kf_map is None:
            return self._bootstrap(frame, index, timings)
        start = time.perf_counter()
        tracked = self._backend.track(frame.image, kf_map.cache, heads=self._config.heads)
        timings["track"] = _ms(start)
        pose = Pose(kf_map.gauge.apply_to_pose(tracked.pose))
        confidence = frame_confidence(tracked.confidence, tracked.confidence_map, frame.mask)
        verdict = self._monitor.update(confidence, relocalizing=self.state is _S.RELOCALIZING)
        self._react(verdict.lost, verdict.recovered, verdict.timed_out, index)
        if self._keeper.map is None:  # a timeout policy dropped the map
            if self.state is _S.MAPPING:
                return self._bootstrap(frame, index, timings)
            return None, False, confidence, None
        valid = self.state is _S.TRACKING and verdict.confident
        if valid and self._keeper.wants_keyframe(pose.T_world_cam, index):
            keyframe_id = self._keeper.propose(self._backend, frame, index, pose.T_world_cam)
            outcome = self._collect(index, timings) if keyframe_id is not None else None
            if (
                outcome is not None
                and outcome.accepted
                and self._keeper.map is not None
                and outcome.request.candidate.keyframe_id == keyframe_id
            ):
                keyframe = self._keeper.map.keyframe(keyframe_id)
                return Pose(keyframe.T_world_cam), True, confidence, keyframe_id
        return pose, valid, confidence, None

    def _bootstrap(
        self, frame: PreparedFrame, index: int, timings: dict[str, float]
    ) -> tuple[Pose | None, bool, float | None, int | None]:
        """No map: this frame starts the first map (or a new one) unless one is being built."""
        if self.state is _S.INIT:
            self._change(_S.MAPPING, _R.BOOTSTRAP, index)
        if not self._keeper.rebuilding:  # also retries after a failed bootstrap
            cause = "new_map" if self.reason is _R.NEW_MAP else "bootstrap"
            self._keeper.start_bootstrap(self._backend, frame, index, cause)
            self._collect(index, timings)
        if self._keeper.map is None:
            return None, False, None, None
        keyframe0 = self._keeper.map.keyframes[0]
        return Pose(keyframe0.T_world_cam), True, keyframe0.mean_confidence, keyframe0.keyframe_id

    def _react(self, lost: bool, recovered: bool, timed_out: bool, index: int) -> None:
        """Confidence verdict -> state transitions (and the timeout policy)."""
        state = self.state
        if state is _S.TRACKING and lost:
            self._change(_S.RELOCALIZING, _R.LOW_CONFIDENCE, index)
        elif state is _S.RELOCALIZING and recovered:
            self._change(_S.TRACKING, _R.RELOCALIZED, index)
        elif state is _S.RELOCALIZING and timed_out:
            policy_ = self._config.relocalization.timeout_policy
            if policy_ is TimeoutPolicy.STAY:
                self._change(_S.RELOCALIZING, _R.TIMEOUT, index)
            else:
                self._drop_map()
                if policy_ is TimeoutPolicy.RESET:
                    self._change(_S.INIT, _R.TIMEOUT, index)
                else:
                    self._change(_S.MAPPING, _R.NEW_MAP, index)

    def _collect(
        self, index: int, timings: dict[str, float], *, timeout: float | None = 0.0
    ) -> RebuildOutcome | None:
        """Take a finished rebuild (installed by the keeper if accepted) and queue its events."""
        outcome = self._keeper.collect(self._backend, index, timeout=timeout)
        if outcome is None:
            return None
        timings["map"] = outcome.map_ms
        new_map, request = outcome.new_map, outcome.request
        candidate = new_map.keyframes[-1]
        if not outcome.accepted:
            self._events.post(EventKind.KEYFRAME_REJECTED, KeyframeRejectedEvent(
                candidate.keyframe_id, candidate.frame_index, outcome.candidate_confidence,
                outcome.reference_confidence, self._config.rejection.ratio))
            return outcome
        self._monitor.set_reference(new_map.keyframes[0].mean_confidence)
        self._events.post(EventKind.KEYFRAME, KeyframeEvent.of(candidate, new_map.generation))
        self._events.post(EventKind.MAP_UPDATED, MapUpdatedEvent.of(
            new_map, request.cause, request.evicted, outcome.correction))
        if self.state is _S.MAPPING:
            reason = _R.NEW_MAP if request.cause == "new_map" else _R.BOOTSTRAP
            self._change(_S.TRACKING, reason, index)
        return outcome

    # ------------------------------------------------------------------ plumbing
    def _change(self, target: TrackingState, reason: StateReason, index: int | None) -> None:
        """The one place the state changes (through the transition table)."""
        move = transition(self.state, target, reason)
        self._status = (move.state, move.reason)
        self._monitor.reset()
        self._events.post(
            EventKind.STATE_CHANGE, StateChangeEvent(move.previous, move.state, move.reason, index)
        )

    def _settled_map(self) -> KeyframeMap | None:
        """The map once a pending rebuild is installed (not for callers holding the lock)."""
        with self._call():
            self._settle(timeout=None)
            return self._keeper.map

    def _settle(self, timeout: float | None) -> bool:
        """Collect rebuilds until none is pending (a collected one may start the waiting
        keyframe's); True when settled within ``timeout`` seconds (None: however long it takes)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        index = max(self._frames - 1, 0)
        while self._keeper.rebuilding:
            left = None if deadline is None else max(deadline - time.monotonic(), 0.0)
            if self._collect(index, {}, timeout=left) is None:
                return False  # timed out
        return True

    def _drop_map(self) -> None:
        self._keeper.drop()
        self._last_pose = None

    @contextmanager
    def _call(self) -> Iterator[None]:
        """Hold the lock for a public call on an open tracker; deliver the events it queued after
        releasing the lock (also when the call raised: the app must learn of a state change)."""
        try:
            with self._lock:
                if self._closed:
                    raise StateError("the tracker is closed")
                yield
        finally:
            self._events.deliver()

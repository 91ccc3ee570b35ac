"""Tracker events: immutable payloads and a callback registry that never lets a callback break
tracking.

Threading: callbacks run synchronously on the thread that called the ``Tracker`` method causing
the event (``push_frame``, ``wait_for_map``, ``reset``, ...), after the tracker has released its
internal lock — so a callback may call back into the tracker. With asynchronous mapping a rebuild
finishes on the worker thread, but its events are delivered by the next ``push_frame`` (or
``wait_for_map``) on the caller's thread: callbacks never run on the mapping worker and never run
concurrently with each other for one tracker, provided the app calls it from one thread.

An exception raised by a callback is logged (with traceback) under ``kvtracker_sdk.tracking.core.events``
and swallowed: a broken UI callback must not stop the camera loop. Every event is also logged when
it happens, as a structured INFO line (``state_change``, ``keyframe``, ``keyframe_rejected``,
``map_updated``, ``world_frame_changed``, ``backend_failed``) carrying the payload's scalar fields.
"""

from __future__ import annotations

import dataclasses
import enum
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from kvtracker_sdk.cache.keyframe_map import Keyframe, KeyframeMap
from kvtracker_sdk.errors import BackendError
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.tracking.core.gauge import Correction
from kvtracker_sdk.types import StateReason, TrackingState
from kvtracker_sdk.world import WorldAlignment

__all__ = [
    "BackendFailedEvent",
    "EventBus",
    "EventKind",
    "KeyframeEvent",
    "KeyframeRejectedEvent",
    "MapUpdatedEvent",
    "StateChangeEvent",
    "Subscription",
    "WorldFrameChangedEvent",
]

_log = get_logger(__name__)


class EventKind(str, enum.Enum):
    KEYFRAME = "on_keyframe"
    KEYFRAME_REJECTED = "on_keyframe_rejected"
    STATE_CHANGE = "on_state_change"
    MAP_UPDATED = "on_map_updated"
    WORLD_FRAME_CHANGED = "on_world_frame_changed"
    BACKEND_FAILED = "on_backend_failed"
    # the live intake's (``Tracker.submit``), emitted on its worker thread, never queued or logged
    RESULT = "on_result"  # a ``FrameResult`` of a frame it processed
    FRAME_ERROR = "on_frame_error"  # the exception ``push_frame`` raised on a frame it took


def _frozen_array(array: np.ndarray) -> np.ndarray:
    out = np.array(array, dtype=np.float64, copy=True)
    out.setflags(write=False)
    return out


@dataclass(frozen=True)
class StateChangeEvent:
    """The tracker moved from ``previous`` to ``state`` (one row of the transition table)."""

    previous: TrackingState
    state: TrackingState
    reason: StateReason
    frame_index: int | None  # the frame being processed, None for reset()/initialize()


@dataclass(frozen=True)
class KeyframeEvent:
    """A frame became a keyframe (its rebuild was accepted). Pose in the world frame."""

    keyframe_id: int
    frame_index: int
    timestamp: float | None
    T_world_cam: np.ndarray  # float64 [4, 4], read-only
    mean_confidence: float
    map_generation: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "T_world_cam", _frozen_array(self.T_world_cam))

    @classmethod
    def of(cls, keyframe: Keyframe, generation: int) -> KeyframeEvent:
        return cls(
            keyframe.keyframe_id,
            keyframe.frame_index,
            keyframe.timestamp,
            keyframe.T_world_cam,
            keyframe.mean_confidence,
            generation,
        )


@dataclass(frozen=True)
class KeyframeRejectedEvent:
    """A candidate keyframe was rejected and the previous map (and cache) kept.

    Also sent for a new map's first frame (after a relocalisation timeout) that did not reach the
    absolute confidence floor: then ``reference_confidence`` is that floor (relaxed once after a few
    such rejections in a row: docs/states.md) and ``ratio`` is 1.
    """

    keyframe_id: int  # the id the candidate would have had (never reused)
    frame_index: int
    confidence: float  # the candidate's (masked) mean confidence in the rebuild
    reference_confidence: float  # keyframe 0's in the same rebuild
    ratio: float  # the configured rejection ratio


@dataclass(frozen=True)
class MapUpdatedEvent:
    """A new map was installed (bootstrap, accepted rebuild, loaded map, new map), or the map was
    re-expressed in a metric or levelled world (cause "world": see ``WorldFrameChangedEvent``).

    ``gauge`` maps the new mapping pass's raw frame to the world frame. ``corrections`` holds, per
    keyframe id kept from the previous map, the rigid world-frame correction ``C`` with
    ``T_new = C @ T_old`` (float64 [4, 4], read-only); the max translation / rotation of those
    corrections summarise how much the map moved.
    """

    generation: int
    cause: str  # "bootstrap", "keyframe", "new_map", "loaded", "world"
    keyframe_ids: tuple[int, ...]
    evicted_ids: tuple[int, ...]
    gauge: Sim3
    corrections: Mapping[int, np.ndarray] = field(default_factory=dict)
    max_translation_correction: float = 0.0  # world units
    max_rotation_correction_deg: float = 0.0

    def __post_init__(self) -> None:
        frozen = {int(k): _frozen_array(v) for k, v in self.corrections.items()}
        object.__setattr__(self, "corrections", MappingProxyType(frozen))

    @classmethod
    def of(
        cls,
        kf_map: KeyframeMap,
        cause: str,
        evicted: tuple[int, ...] = (),
        correction: Correction | None = None,
    ) -> MapUpdatedEvent:
        if correction is None:
            return cls(kf_map.generation, cause, kf_map.keyframe_ids, evicted, kf_map.gauge)
        return cls(
            kf_map.generation,
            cause,
            kf_map.keyframe_ids,
            evicted,
            kf_map.gauge,
            correction.transforms,
            correction.max_translation,
            correction.max_rotation_deg,
        )


@dataclass(frozen=True)
class WorldFrameChangedEvent:
    """A map in a NEW world frame was installed: poses before and after it are not comparable.

    Sent after a map was dropped and another one started (``reason``: TIMEOUT for the ``reset``
    timeout policy, NEW_MAP for ``new_map``, RESET for ``reset()``) or a saved map replaced one
    (MAP_LOADED). Rebuilds of one map keep its world frame and never send this.

    Also sent when the world was re-expressed in metres or levelled (``reason``: a
    ``WorldAlignment``, METRIC_SCALE or GRAVITY): then ``transform`` (new world <- old world, a
    Sim(3) about the origin) moves anything the app placed in the old world into the new one:
    ``transform.apply_to_points(p)``, ``transform.apply_to_pose(T)``. It is None for an unrelated
    new world.
    """

    reason: StateReason | WorldAlignment
    previous_generation: int  # the last map of the old world frame (0: none)
    generation: int  # the first map of the new world frame
    frame_index: int | None  # the frame that built it (None for a loaded map)
    transform: Sim3 | None = None


@dataclass(frozen=True)
class BackendFailedEvent:
    """A backend call failed; the tracker carried on (sent once per failed call).

    ``operation`` is "map" (a rebuild or bootstrap: the current map is kept and no mapping pass
    starts before ``retry_at_frame``) or "track" (this frame got no pose). ``error`` is the typed
    error (``MappingFailedError``/``TrackingFailedError``) whose ``__cause__`` is the original.
    """

    operation: str
    frame_index: int  # the frame being mapped or tracked
    message: str
    error: BackendError
    consecutive: int  # failures of this operation in a row, this one included
    retry_at_frame: int | None = None


Event = (
    StateChangeEvent
    | KeyframeEvent
    | KeyframeRejectedEvent
    | MapUpdatedEvent
    | WorldFrameChangedEvent
    | BackendFailedEvent
)
Callback = Callable[[Any], None]


@dataclass(frozen=True, eq=False)
class Subscription:
    """Handle returned by ``register``; ``unregister()`` removes the callback (idempotent)."""

    kind: EventKind
    callback: Callback
    bus: EventBus = field(repr=False)

    def unregister(self) -> None:
        self.bus.unregister(self)


def _log_fields(payload: Event) -> dict[str, Any]:
    """The scalar fields of a payload, for a structured log line (arrays and Sim3 left out)."""
    fields: dict[str, Any] = {}
    for item in dataclasses.fields(payload):
        value = getattr(payload, item.name)
        value = value.value if isinstance(value, enum.Enum) else value
        if value is None or isinstance(value, (int, float, str, tuple)):
            # "timestamp" would be overwritten by the log line's own time stamp
            fields["frame_timestamp" if item.name == "timestamp" else item.name] = value
    return fields


class EventBus:
    """Per-tracker callback registry (thread-safe registration, isolated delivery).

    The tracker ``post``s events while it holds its lock and ``deliver``s them once released.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._subscriptions: dict[EventKind, list[Subscription]] = {kind: [] for kind in EventKind}
        self._posted: list[tuple[EventKind, Event]] = []

    def post(self, kind: EventKind, payload: Event) -> None:
        """Log the event (structured, INFO, named like ``state_change``) and queue it."""
        _log.info(kind.value.removeprefix("on_"), **_log_fields(payload))
        with self._lock:
            self._posted.append((kind, payload))

    def deliver(self) -> None:
        """Emit every posted event, oldest first."""
        with self._lock:
            posted, self._posted = self._posted, []
        for kind, payload in posted:
            self.emit(kind, payload)

    def register(self, kind: EventKind | str, callback: Callback) -> Subscription:
        """Call ``callback(payload)`` for every event of ``kind``; returns the handle."""
        kind = EventKind(kind)
        if not callable(callback):
            raise TypeError(f"callback must be callable, got {type(callback).__name__}")
        subscription = Subscription(kind, callback, self)
        with self._lock:
            self._subscriptions[kind].append(subscription)
        return subscription

    def unregister(self, handle: Subscription | Callback) -> bool:
        """Remove a subscription (or every registration of a callback). True if one was found."""
        found = False
        with self._lock:
            for kind, subscriptions in self._subscriptions.items():
                # == rather than `is`: each `obj.method` access makes a new, equal bound method
                kept = [s for s in subscriptions if s is not handle and s.callback != handle]
                found = found or len(kept) != len(subscriptions)
                self._subscriptions[kind] = kept
        return found

    def count(self, kind: EventKind | str) -> int:
        with self._lock:
            return len(self._subscriptions[EventKind(kind)])

    def emit(self, kind: EventKind, payload: object) -> None:
        """Deliver ``payload`` (an ``Event``; for the live intake's kinds a ``FrameResult`` or an
        exception) to every callback of ``kind`` now, on this thread; a raising callback is
        logged only."""
        with self._lock:
            subscriptions = list(self._subscriptions[kind])  # callbacks may (un)register
        for subscription in subscriptions:
            try:
                subscription.callback(payload)
            except Exception:
                _log.exception(
                    "callback_failed",
                    kind=kind.value,
                    callback=getattr(
                        subscription.callback, "__qualname__", repr(subscription.callback)
                    ),
                )


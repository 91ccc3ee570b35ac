"""``tracker.events``: where an app registers callbacks for the tracker's events.

A thin view over the tracker's ``EventBus`` (``core/events.py``): it owns no state and no lock.
Each ``on_*`` method registers a callback and returns a ``Subscription`` (its ``unregister()``
removes it); ``unregister`` removes a subscription or every registration of a callback.

Threads: callbacks run on the thread whose tracker call caused the event, after the tracker has
released its lock; the live intake's ``on_result`` / ``on_frame_error`` run on its worker thread.
An exception raised by a callback is logged, never raised (``core/events.py``).
"""

from __future__ import annotations

from kvtracker_sdk.tracking.core.events import Callback, EventBus, EventKind, Subscription

__all__ = ["TrackerEvents"]


class TrackerEvents:
    """The tracker's callback registrations (``tracker.events``); payloads are immutable."""

    __slots__ = ("_bus",)

    def __init__(self, bus: EventBus) -> None:
        self._bus = bus

    def on_keyframe(self, callback: Callback) -> Subscription:
        """``KeyframeEvent``: a frame became a keyframe."""
        return self._bus.register(EventKind.KEYFRAME, callback)

    def on_keyframe_rejected(self, callback: Callback) -> Subscription:
        """``KeyframeRejectedEvent``: a candidate (or a new map's first frame) was not confident."""
        return self._bus.register(EventKind.KEYFRAME_REJECTED, callback)

    def on_state_change(self, callback: Callback) -> Subscription:
        """``StateChangeEvent``: one row of the state table was taken."""
        return self._bus.register(EventKind.STATE_CHANGE, callback)

    def on_map_updated(self, callback: Callback) -> Subscription:
        """``MapUpdatedEvent``: a new map was installed."""
        return self._bus.register(EventKind.MAP_UPDATED, callback)

    def on_world_frame_changed(self, callback: Callback) -> Subscription:
        """``WorldFrameChangedEvent``: poses from now on are in a new world frame."""
        return self._bus.register(EventKind.WORLD_FRAME_CHANGED, callback)

    def on_backend_failed(self, callback: Callback) -> Subscription:
        """``BackendFailedEvent``: a mapping or tracking pass failed; tracking carried on."""
        return self._bus.register(EventKind.BACKEND_FAILED, callback)

    def on_result(self, callback: Callback) -> Subscription:
        """``FrameResult`` of each frame the live intake (``tracker.submit``) processed, on its
        worker thread."""
        return self._bus.register(EventKind.RESULT, callback)

    def on_frame_error(self, callback: Callback) -> Subscription:
        """The exception the live intake's ``push_frame`` raised on a frame (a bad frame), on its
        worker thread."""
        return self._bus.register(EventKind.FRAME_ERROR, callback)

    def unregister(self, handle: Subscription | Callback) -> bool:
        """Remove a subscription (or every registration of a callback); True if one was found."""
        return self._bus.unregister(handle)

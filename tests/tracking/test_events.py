"""EventBus: registration, isolation of failing callbacks, immutable payloads."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.tracking.core.events import (
    EventBus,
    EventKind,
    KeyframeEvent,
    MapUpdatedEvent,
    StateChangeEvent,
)
from kvtracker_sdk.types import StateReason, TrackingState


def _state_event() -> StateChangeEvent:
    return StateChangeEvent(TrackingState.INIT, TrackingState.MAPPING, StateReason.BOOTSTRAP, 0)


def test_register_emit_unregister() -> None:
    bus = EventBus()
    seen: list[object] = []
    subscription = bus.register(EventKind.STATE_CHANGE, seen.append)
    bus.emit(EventKind.STATE_CHANGE, _state_event())
    bus.emit(EventKind.KEYFRAME, _state_event())  # another kind: not delivered
    assert len(seen) == 1
    subscription.unregister()
    bus.emit(EventKind.STATE_CHANGE, _state_event())
    assert len(seen) == 1
    assert bus.count(EventKind.STATE_CHANGE) == 0


def test_unregister_by_callback_removes_every_registration() -> None:
    bus = EventBus()
    seen: list[object] = []
    bus.register("on_state_change", seen.append)
    bus.register(EventKind.MAP_UPDATED, seen.append)
    assert bus.unregister(seen.append) is True
    assert bus.unregister(seen.append) is False
    bus.emit(EventKind.STATE_CHANGE, _state_event())
    assert seen == []


def test_a_raising_callback_is_logged_and_the_others_still_run(
    caplog: pytest.LogCaptureFixture,
) -> None:
    bus = EventBus()
    seen: list[object] = []

    def broken(_: object) -> None:
        raise RuntimeError("UI exploded")

    bus.register(EventKind.STATE_CHANGE, broken)
    bus.register(EventKind.STATE_CHANGE, seen.append)
    with caplog.at_level(logging.ERROR, logger="kvtracker_sdk"):
        bus.emit(EventKind.STATE_CHANGE, _state_event())
    assert len(seen) == 1
    assert any(
        record.exc_info and "UI exploded" in str(record.exc_info[1]) for record in caplog.records
    )


def test_callback_may_unregister_itself_during_delivery() -> None:
    bus = EventBus()
    calls: list[int] = []

    def once(_: object) -> None:
        calls.append(1)
        bus.unregister(once)

    bus.register(EventKind.KEYFRAME, once)
    bus.emit(EventKind.KEYFRAME, _state_event())
    bus.emit(EventKind.KEYFRAME, _state_event())
    assert calls == [1]


def test_non_callable_is_refused() -> None:
    with pytest.raises(TypeError):
        EventBus().register(EventKind.KEYFRAME, 42)  # type: ignore[arg-type]


def test_payloads_are_immutable_and_copy_arrays() -> None:
    pose = np.eye(4)
    event = KeyframeEvent(3, 150, 1.5, pose, 0.7, 2)
    pose[0, 3] = 99.0  # the caller's array changes; the event must not
    assert event.T_world_cam[0, 3] == 0.0
    with pytest.raises(ValueError):
        event.T_world_cam[0, 0] = 2.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        event.keyframe_id = 4  # type: ignore[misc]
    update = MapUpdatedEvent(2, "keyframe", (0, 3), (1,), Sim3.identity(), {0: np.eye(4)})
    with pytest.raises(TypeError):
        update.corrections[5] = np.eye(4)  # type: ignore[index]
    with pytest.raises(ValueError):
        update.corrections[0][0, 0] = 3.0

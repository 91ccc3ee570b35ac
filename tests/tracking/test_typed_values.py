"""Typed values where strings and long positional tuples were: ``FrameResult`` is built by keyword,
a rebuild's cause is an enum whose value is what events and logs say, ``MapStatus`` is built from
named fields."""

from __future__ import annotations

import json

import pytest

from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.tracking.mapping.map_builder import RebuildCause
from kvtracker_sdk.types import FrameResult, StateReason, TrackingState
from tests.tracking.gated_backend import GatedBackend
from tests.tracking.sim_session import drive, make_tracker


def test_a_frame_result_is_built_by_keyword_only() -> None:
    fields = {"frame_index": 0, "timestamp": 0.0, "state": TrackingState.INIT,
              "reason": StateReason.NONE, "pose": None, "pose_valid": False, "confidence": None}
    assert FrameResult(**fields).frame_index == 0
    with pytest.raises(TypeError):
        FrameResult(*fields.values())  # type: ignore[misc]


def test_rebuild_causes_are_an_enum_that_events_and_logs_report_as_before() -> None:
    assert [c.value for c in RebuildCause] == ["bootstrap", "keyframe", "new_map"]
    assert str(RebuildCause.NEW_MAP) == f"{RebuildCause.NEW_MAP}" == "new_map"
    assert json.dumps(RebuildCause.KEYFRAME) == '"keyframe"'
    backend = GatedBackend(orbit(25, turns=0.2), seed=3)
    with make_tracker(backend, keyframing={"interval_frames": 10}) as tracker:
        session = drive(tracker, backend, stop=25)
        status = tracker.map_status
    causes = [event.cause for event in session.maps]
    assert causes[:2] == ["bootstrap", "keyframe"]
    assert all(type(cause) is str for cause in causes)  # the public event keeps plain strings
    assert status.keyframe_ids == (0, 1, 2) and not status.rebuilding
    assert status.retry_at_frame is None and status.world == tracker.keyframe_map.world

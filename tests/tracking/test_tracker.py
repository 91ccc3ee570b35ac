"""Tracker API: life cycle, results, events, reset/close, backend swap, the loaded-map seam."""

from __future__ import annotations

import logging
import threading

import numpy as np
import pytest

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.errors import BackendMismatchError, StateError
from kvtracker_sdk.types import HeadSet, StateReason, TrackingState
from tests.tracking.sim_session import SIZE, Session, drive, make_tracker


@pytest.fixture(scope="module")
def backend() -> SimulatedBackend:
    return SimulatedBackend(orbit(600, turns=0.5), seed=4)


def test_first_frame_bootstraps_the_map_at_the_identity(backend: SimulatedBackend) -> None:
    with make_tracker(backend) as tracker:
        assert (tracker.state, tracker.reason) == (TrackingState.INIT, StateReason.NONE)
        assert tracker.get_pose() is None and tracker.map_status.num_keyframes == 0
        session = drive(tracker, backend, stop=1)
        first = session.results[0]
        assert session.moves() == [
            ("INIT", "MAPPING", "BOOTSTRAP", 0),
            ("MAPPING", "TRACKING", "BOOTSTRAP", 0),
        ]
        assert first.state is TrackingState.TRACKING and first.pose_valid and first.keyframe_id == 0
        # exact, not close: keyframe 0's camera is the world frame by definition (the raw pose
        # inverted and applied to itself is the identity only to rounding, ~1e-16 here)
        np.testing.assert_array_equal(first.pose.T_world_cam, np.eye(4))
        np.testing.assert_array_equal(tracker.keyframe_map.keyframes[0].T_world_cam, np.eye(4))
        assert tracker.get_pose() is first.pose
        assert first.map_generation == 1 and {"preprocess", "map", "total"} <= set(first.timings_ms)
        assert session.maps[0].cause == "bootstrap" and session.keyframes[0].keyframe_id == 0


def test_scene_mode_adds_a_keyframe_every_interval(backend: SimulatedBackend) -> None:
    with make_tracker(backend, keyframing={"interval_frames": 20}) as tracker:
        session = drive(tracker, backend, stop=70)
        assert [r.frame_index for r in session.results if r.is_keyframe] == [0, 20, 40, 60]
        assert tracker.map_status.keyframe_ids == (0, 1, 2, 3)
        assert tracker.keyframe_map.cache.keyframe_ids == (0, 1, 2, 3)  # relabelled pass ids
        assert session.results[-1].map_generation == 4
        tracked = session.results[5]
        assert tracked.keyframe_id is None and "track" in tracked.timings_ms
        assert tracked.confidence == pytest.approx(session.keyframes[0].mean_confidence, rel=0.05)
        assert session.maps[1].corrections.keys() == {0}  # keyframe 0 was shared and corrected


def test_reset_returns_to_init_and_never_reuses_ids(backend: SimulatedBackend) -> None:
    with make_tracker(backend, keyframing={"interval_frames": 20}) as tracker:
        session = drive(tracker, backend, stop=25)
        tracker.reset()
        assert (tracker.state, tracker.reason) == (TrackingState.INIT, StateReason.RESET)
        assert tracker.get_pose() is None and tracker.keyframe_map is None
        assert session.moves()[-1] == ("TRACKING", "INIT", "RESET", None)
        drive(tracker, backend, start=25, stop=26, session=session)
        assert session.results[-1].frame_index == 25  # frame indices keep counting
        assert tracker.map_status.keyframe_ids == (2,)  # ids 0, 1 belong to the first map
        tracker.initialize()  # a fresh session again
        assert tracker.state is TrackingState.INIT


def test_closed_tracker_refuses_frames_and_close_is_idempotent(backend: SimulatedBackend) -> None:
    tracker = make_tracker(backend, threading={"async_mapping": True})
    drive(tracker, backend, stop=2)
    tracker.close()
    tracker.close()
    frame = backend.camera(SIZE, textured=False).render(3)
    with pytest.raises(StateError, match="closed"):
        tracker.push_frame(frame.image)
    with pytest.raises(StateError):
        tracker.reset()


def test_callback_errors_never_break_tracking(backend: SimulatedBackend) -> None:
    def broken(_: object) -> None:
        raise RuntimeError("app bug")

    with make_tracker(backend, keyframing={"interval_frames": 10}) as tracker:
        tracker.events.on_keyframe(broken)
        tracker.events.on_state_change(broken)
        subscription = tracker.events.on_map_updated(broken)
        session = drive(tracker, backend, stop=30)
        assert all(r.pose_valid for r in session.results)
        assert len(session.keyframes) == 3
        assert tracker.events.unregister(subscription) is True


def test_async_callbacks_run_on_the_calling_thread(backend: SimulatedBackend) -> None:
    threads: set[str] = set()
    with make_tracker(
        backend, threading={"async_mapping": True}, keyframing={"interval_frames": 10}
    ) as tracker:
        tracker.events.on_keyframe(lambda _: threads.add(threading.current_thread().name))
        tracker.events.on_map_updated(lambda _: threads.add(threading.current_thread().name))
        drive(tracker, backend, stop=60)
        assert tracker.wait_for_map(timeout=30)
    assert threads == {threading.current_thread().name}


def test_camera_head_only_disables_loss_detection() -> None:
    lossy = SimulatedBackend(orbit(120), loss_segments=[(20, 60)])
    with make_tracker(lossy, heads="camera") as tracker:
        session = drive(tracker, lossy, stop=80)
    assert tracker.config.heads is HeadSet.CAMERA
    assert all(r.confidence is None for r in session.results[1:])
    assert all(r.state is TrackingState.TRACKING for r in session.results)


def test_set_backend_swaps_equal_functions_and_refuses_others(backend: SimulatedBackend) -> None:
    twin = SimulatedBackend(orbit(600, turns=0.5), seed=4)
    stranger = SimulatedBackend(orbit(600, turns=0.5), seed=5)
    with make_tracker(backend) as tracker:
        session = drive(tracker, backend, stop=10)
        assert tracker.set_backend(twin) is backend
        drive(tracker, twin, start=10, stop=20, session=session)
        assert all(r.pose_valid for r in session.results)
        with pytest.raises(BackendMismatchError) as info:
            tracker.set_backend(stranger)
        assert backend.info.fingerprint in str(info.value) and stranger.info.fingerprint in str(
            info.value
        )
        assert tracker.backend is twin


def test_loaded_map_relocalises_in_the_saved_world_frame(backend: SimulatedBackend) -> None:
    with make_tracker(backend, keyframing={"interval_frames": 20}) as first:
        drive(first, backend, stop=61)
        saved = first.keyframe_map
        reference = drive(first, backend, start=100, stop=110)
    with make_tracker(
        backend, relocalization={"recover_after": 3}, keyframing={"interval_frames": 20}
    ) as second:
        session = Session().listen(second)
        second._install_loaded_map(saved)
        assert (second.state, second.reason) == (TrackingState.RELOCALIZING, StateReason.MAP_LOADED)
        assert (
            session.maps[0].cause == "loaded" and second.map_status.generation == saved.generation
        )
        drive(second, backend, start=100, stop=130, session=session)
    assert ("RELOCALIZING", "TRACKING", "RELOCALIZED", 2) in session.moves()  # 3rd frame
    assert [r.pose_valid for r in session.results[:3]] == [False, False, True]
    # same cache, same gauge: the same poses as the session that built the map
    for ours, theirs in zip(session.results[:2], reference.results[:2], strict=True):
        np.testing.assert_allclose(ours.pose.T_world_cam, theirs.pose.T_world_cam, atol=1e-9)
    # the keyframe interval counts from the first confident frame of the new session (it
    # used to make that frame a keyframe at once); ids continue after the map's
    assert [r.frame_index for r in session.results if r.is_keyframe] == [22]
    assert session.results[22].keyframe_id == 4
    assert second.map_status.keyframe_ids == (0, 1, 2, 3, 4)


def test_frames_and_state_changes_are_structured_log_events(
    backend: SimulatedBackend, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    with make_tracker(backend) as tracker:
        drive(tracker, backend, stop=3)  # logging not configured: the library stays silent
        assert capsys.readouterr() == ("", "")
        with caplog.at_level(logging.DEBUG, logger="kvtracker_sdk"):
            tracker.reset()
            drive(tracker, backend, start=3, stop=5)
    frames = [r for r in caplog.records if r.getMessage() == "frame"]
    changes = [r for r in caplog.records if r.getMessage() == "state_change"]
    assert [r.frame_index for r in frames] == [3, 4]
    assert all(r.total_ms > 0 and r.preprocess_ms >= 0 for r in frames)
    assert [(r.previous, r.state, r.reason) for r in changes] == [
        ("TRACKING", "INIT", "RESET"),
        ("INIT", "MAPPING", "BOOTSTRAP"),
        ("MAPPING", "TRACKING", "BOOTSTRAP"),
    ]


# Mapping and tracking failures (a failed bootstrap, a failed rebuild): test_tracker_failures.py

"""What asynchronous mapping does with a keyframe candidate that arrives during a rebuild: it waits
for that rebuild and starts right after the swap, so the keyframes of a trajectory depend on its
frames, not on the CPU (``tracking/mapping/map_keeper.py``). The gated backend makes the test, not the
machine, decide when each mapping pass finishes."""

from __future__ import annotations

import pytest

from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.tracking.facade.tracker import Tracker
from tests.tracking.gated_backend import GatedBackend
from tests.tracking.sim_session import WAIT_S, Session, drive, make_tracker

INTERVAL = 10


def _tracker(backend: GatedBackend, async_mapping: bool) -> Tracker:
    config = {
        "threading": {"async_mapping": async_mapping},
        "keyframing": {"interval_frames": INTERVAL},
    }
    return make_tracker(backend, **config)


def _keyframe_frames(session: Session) -> list[int]:
    return [k.frame_index for k in session.keyframes]


@pytest.mark.parametrize("async_mapping", [False, True], ids=["sync", "async"])
def test_a_candidate_during_a_rebuild_waits_and_keeps_the_keyframes_of_sync_mapping(
    async_mapping: bool,
) -> None:
    backend = GatedBackend(orbit(60, turns=0.2), seed=3)
    if async_mapping:
        backend.hold(2)  # keyframe 1 (frame 10) stays on the worker until released
    with _tracker(backend, async_mapping) as tracker:
        session = drive(tracker, backend, stop=1, settle=True)
        drive(tracker, backend, start=1, stop=25, session=session)
        status = tracker.map_status
        if async_mapping:
            # frame 10's rebuild is held; frame 20 qualified meanwhile and waits for it
            assert backend.started(2)
            assert status.rebuilding and status.keyframe_waiting
            assert status.keyframe_ids == (0,) and _keyframe_frames(session) == [0]
            assert all(r.pose_valid for r in session.results[1:])  # tracking went on
            backend.release(2)
        else:
            # inline rebuilds finish within the frame that proposed them: nothing ever waits
            assert not status.rebuilding and not status.keyframe_waiting
            assert _keyframe_frames(session) == [0, 10, 20]
        drive(tracker, backend, start=25, stop=26, session=session)  # frame 10's map swaps in
        assert tracker.wait_for_map(timeout=WAIT_S)  # frame 20's rebuild started after the swap
        assert _keyframe_frames(session) == [0, 10, 20]
        drive(tracker, backend, start=26, stop=60, session=session, pace=True)
        assert tracker.wait_for_map(timeout=WAIT_S)
        assert _keyframe_frames(session) == [0, 10, 20, 30, 40, 50]
        assert [k.keyframe_id for k in session.keyframes] == [0, 1, 2, 3, 4, 5]
        assert tracker.map_status.deferred_replaced == 0


def test_a_rebuild_slower_than_an_interval_replaces_the_waiting_candidate_and_counts_it() -> None:
    backend = GatedBackend(orbit(60, turns=0.2), seed=3)
    backend.hold(2)
    with _tracker(backend, async_mapping=True) as tracker:
        session = drive(tracker, backend, stop=1, settle=True)
        drive(tracker, backend, start=1, stop=35, session=session)
        assert backend.started(2)
        status = tracker.map_status
        # frames 20 and 30 both qualified while frame 10's pass was held: the newer one waits
        assert status.keyframe_waiting and status.deferred_replaced == 1
        backend.release(2)
        assert tracker.wait_for_map(timeout=WAIT_S)
        assert _keyframe_frames(session) == [0, 10, 30]
        assert [k.keyframe_id for k in session.keyframes] == [0, 1, 2]  # no id was burnt

"""The map keeper's rebuild cycle: its table, and the phases a keeper really passes through."""

from __future__ import annotations

import itertools

import pytest

from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.errors import IllegalTransitionError
from kvtracker_sdk.tracking.mapping.rebuild_cycle import (
    MOVES,
    RebuildEvent,
    RebuildPhase,
    check_move,
)
from tests.tracking.gated_backend import GatedBackend
from tests.tracking.sim_session import WAIT_S, drive, make_tracker

P, E = RebuildPhase, RebuildEvent


def test_moves_outside_the_table_raise() -> None:
    for before, event, after in itertools.product(RebuildPhase, RebuildEvent, RebuildPhase):
        if after in MOVES.get((before, event), frozenset()):
            check_move(before, event, after)
        else:
            with pytest.raises(IllegalTransitionError, match="illegal rebuild move"):
                check_move(before, event, after)
    # every phase is reachable and can be left
    assert {p for targets in MOVES.values() for p in targets} == set(RebuildPhase)
    assert {p for p, _ in MOVES} == set(RebuildPhase)


def test_a_held_rebuild_walks_idle_building_candidate_waiting_and_back() -> None:
    """Every move of a real session is also checked inside the keeper against the table; the
    gated backend makes the test decide when the mapping pass of keyframe 1 finishes."""
    backend = GatedBackend(orbit(40, turns=0.2), seed=3)
    backend.hold(2)  # keyframe 1 (frame 10) stays on the worker until released
    config = {"threading": {"async_mapping": True}, "keyframing": {"interval_frames": 10}}
    with make_tracker(backend, **config) as tracker:
        keeper = tracker._keeper
        assert keeper.phase is P.IDLE
        session = drive(tracker, backend, stop=1, settle=True)
        assert keeper.phase is P.IDLE  # the first map is installed
        drive(tracker, backend, start=1, stop=15, session=session)
        assert keeper.phase is P.BUILDING  # frame 10's pass is held
        drive(tracker, backend, start=15, stop=25, session=session)
        assert keeper.phase is P.CANDIDATE_WAITING  # frame 20 waits for it
        backend.release(2)
        assert tracker.wait_for_map(timeout=WAIT_S)
        assert keeper.phase is P.IDLE
        drive(tracker, backend, start=25, stop=32, session=session)
        tracker.reset()
        assert keeper.phase is P.IDLE

"""The transition table: every legal move passes, every other (state, state, reason) raises."""

from __future__ import annotations

import itertools

import pytest

from kvtracker_sdk.errors import IllegalTransitionError, StateError
from kvtracker_sdk.tracking.loop.states import TRANSITIONS, Transition, transition
from kvtracker_sdk.types import StateReason, TrackingState

S, R = TrackingState, StateReason

LEGAL = sorted(
    ((a, b, r) for (a, b), reasons in TRANSITIONS.items() for r in reasons),
    key=lambda t: (t[0].value, t[1].value, t[2].value),
)
ALL = list(itertools.product(TrackingState, TrackingState, StateReason))


@pytest.mark.parametrize(("current", "target", "reason"), LEGAL)
def test_legal_transitions_return_the_move(current: S, target: S, reason: R) -> None:
    assert transition(current, target, reason) == Transition(current, target, reason)


def test_every_other_combination_raises() -> None:
    legal = set(LEGAL)
    illegal = [t for t in ALL if t not in legal]
    assert len(illegal) == len(ALL) - len(legal) > 100  # the table is sparse
    for current, target, reason in illegal:
        with pytest.raises(IllegalTransitionError, match=f"{current.value} -> {target.value}"):
            transition(current, target, reason)


def test_illegal_transition_is_a_state_error() -> None:
    with pytest.raises(StateError):
        transition(S.INIT, S.TRACKING, R.BOOTSTRAP)  # no localisation without a map


def test_the_design_doc_life_cycle_is_in_the_table() -> None:
    expected = {
        (S.INIT, S.MAPPING, R.BOOTSTRAP),
        (S.MAPPING, S.TRACKING, R.BOOTSTRAP),
        (S.TRACKING, S.RELOCALIZING, R.LOW_CONFIDENCE),
        (S.RELOCALIZING, S.TRACKING, R.RELOCALIZED),
        (S.RELOCALIZING, S.INIT, R.TIMEOUT),
        (S.RELOCALIZING, S.MAPPING, R.NEW_MAP),
        (S.RELOCALIZING, S.RELOCALIZING, R.TIMEOUT),
        (S.INIT, S.RELOCALIZING, R.MAP_LOADED),
        (S.TRACKING, S.INIT, R.RESET),
    }
    assert expected <= set(LEGAL)


def test_no_transition_uses_reason_none_and_every_reason_but_none_is_used() -> None:
    used = {reason for _, _, reason in LEGAL}
    assert R.NONE not in used
    assert used == set(StateReason) - {R.NONE}


def test_table_is_read_only() -> None:
    with pytest.raises(TypeError):
        TRANSITIONS[(S.INIT, S.TRACKING)] = frozenset({R.BOOTSTRAP})  # type: ignore[index]


def test_the_table_chooses_the_next_state_from_state_and_event() -> None:
    """Every (state, event) pair either moves (NEXT), changes nothing (UNCHANGED) or raises."""
    from kvtracker_sdk.tracking.loop.states import NEXT, UNCHANGED, TrackingEvent, next_state

    assert not set(NEXT) & UNCHANGED
    assert {event for _, event in NEXT} == set(TrackingEvent)  # no event without a move
    for state, event in itertools.product(TrackingState, TrackingEvent):
        if (state, event) in NEXT:
            target, reason = NEXT[(state, event)]
            assert next_state(state, event) == Transition(state, target, reason)
            assert transition(state, target, reason) == Transition(state, target, reason)
        elif (state, event) in UNCHANGED:
            assert next_state(state, event) is None
        else:
            with pytest.raises(IllegalTransitionError, match=f"{event.value} in state"):
                next_state(state, event)
    # the timeout policies are three events, not one reason with a hand-picked target
    assert next_state(S.RELOCALIZING, TrackingEvent.TIMEOUT_STAY).state is S.RELOCALIZING
    assert next_state(S.RELOCALIZING, TrackingEvent.TIMEOUT_RESET).state is S.INIT
    assert next_state(S.RELOCALIZING, TrackingEvent.TIMEOUT_NEW_MAP).state is S.MAPPING

"""The map-rebuild cycle: the ``MapKeeper``'s phases and the one table of their legal moves.

A keeper is in one ``RebuildPhase`` at a time, read from what it holds (``MapKeeper.phase``):

* ``IDLE``: no mapping pass pending (a rejected candidate's wait, ``rejection.retry_after_frames``,
  is a frame count inside this phase: it gates new keyframes, not the phase);
* ``BUILDING``: a pass (bootstrap, new map or keyframe; a full rebuild or an insertion) was started
  and its result not taken yet (running on the mapping worker, or finished inline);
* ``CANDIDATE_WAITING``: a pass is pending and a newer keyframe candidate waits for it in the one
  slot; its pass starts when the pending one is taken (unless it fell into a wait);
* ``FAILED``: the last pass failed; none starts before ``MapStatus.retry_at_frame`` (a backoff that
  grows while failures repeat).

Taking a finished pass is one ``RebuildEvent`` (accepted: the new map is installed by one
reference assignment; rejected; failed), after which the waiting candidate's pass, if any, starts
at once: so from ``CANDIDATE_WAITING`` the table allows two next phases, chosen by whether the
waiting candidate may start. Every move the keeper makes is checked against ``MOVES``
(``check_move``); a move missing from it is a bug and raises ``IllegalTransitionError``.
``rebuild_diagram.mermaid_rebuild_diagram`` draws the table for ``docs/states.md`` (a test
compares them).
"""

from __future__ import annotations

import enum
from types import MappingProxyType

from kvtracker_sdk.errors import IllegalTransitionError

__all__ = ["MOVES", "RebuildEvent", "RebuildPhase", "check_move"]


class RebuildPhase(enum.Enum):
    """Where the keeper's map-rebuild cycle is."""

    IDLE = "IDLE"
    BUILDING = "BUILDING"
    CANDIDATE_WAITING = "CANDIDATE_WAITING"
    FAILED = "FAILED"


class RebuildEvent(enum.Enum):
    """What moved the rebuild cycle."""

    START = "start"  # a pass starts: bootstrap, new map, or a keyframe candidate
    DEFER = "defer"  # a keyframe candidate arrives while a pass is pending: it waits
    REPLACE = "replace"  # a newer candidate replaces the waiting one (an overloaded worker)
    ACCEPT = "accept"  # the pending pass is taken and its map installed
    REJECT = "reject"  # the pending pass is taken and its map rejected
    FAIL = "fail"  # the pending pass raised or gave non-finite output: the map stays
    DROP = "drop"  # the map is dropped or replaced by a loaded one; a pending pass is discarded


_P, _E = RebuildPhase, RebuildEvent
_AFTER_TAKEN = frozenset({_P.BUILDING, _P.IDLE})  # the waiting candidate started, or dropped

# (phase, event) -> the phases it may lead to. The only place the rebuild cycle is written.
MOVES: MappingProxyType[tuple[RebuildPhase, RebuildEvent], frozenset[RebuildPhase]] = (
    MappingProxyType(
        {
            (_P.IDLE, _E.START): frozenset({_P.BUILDING}),
            (_P.BUILDING, _E.DEFER): frozenset({_P.CANDIDATE_WAITING}),
            (_P.CANDIDATE_WAITING, _E.REPLACE): frozenset({_P.CANDIDATE_WAITING}),
            (_P.BUILDING, _E.ACCEPT): frozenset({_P.IDLE}),
            (_P.BUILDING, _E.REJECT): frozenset({_P.IDLE}),
            (_P.CANDIDATE_WAITING, _E.ACCEPT): _AFTER_TAKEN,
            (_P.CANDIDATE_WAITING, _E.REJECT): _AFTER_TAKEN,
            (_P.BUILDING, _E.FAIL): frozenset({_P.FAILED}),
            (_P.CANDIDATE_WAITING, _E.FAIL): frozenset({_P.BUILDING, _P.FAILED}),
            # after the backoff, the next pass (a retry, or another candidate) starts from here
            (_P.FAILED, _E.START): frozenset({_P.BUILDING}),
            (_P.IDLE, _E.DROP): frozenset({_P.IDLE}),
            (_P.BUILDING, _E.DROP): frozenset({_P.IDLE}),
            (_P.CANDIDATE_WAITING, _E.DROP): frozenset({_P.IDLE}),
            (_P.FAILED, _E.DROP): frozenset({_P.IDLE}),
        }
    )
)


def check_move(before: RebuildPhase, event: RebuildEvent, after: RebuildPhase) -> None:
    """IllegalTransitionError unless ``event`` in phase ``before`` may lead to ``after``."""
    allowed = MOVES.get((before, event))
    if allowed is None or after not in allowed:
        raise IllegalTransitionError(
            f"illegal rebuild move {before.value} --{event.value}--> {after.value}"
        )

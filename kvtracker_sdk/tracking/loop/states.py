"""The tracker's state machine: one table that chooses the next state from (state, event).

Like ``h11/_state.py``: no I/O, no tracker knowledge, every move listed once. The frame loop
(``frame_loop.FrameLoop.fire``) is the only place the state changes: a call site says what
*happened* (a ``TrackingEvent``: confidence lost, a map built, a timeout under the reset
policy, ...) and ``next_state`` looks up where that leads and with which ``StateReason``. No call
site names a target state. An event the table does not know in the current state is a bug and
raises :class:`~kvtracker_sdk.errors.IllegalTransitionError`; the few events that legitimately
change nothing in some states are listed in ``UNCHANGED``.

``TRANSITIONS`` (the legal (from, to) moves and their reasons) is derived from the table; the
diagrams in ``docs/states.md`` and ``docs/architecture.md`` are drawn from it by
``state_diagram.mermaid_state_diagram`` (a test compares them).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from types import MappingProxyType

from kvtracker_sdk.errors import IllegalTransitionError
from kvtracker_sdk.types import StateReason, TrackingState

__all__ = [
    "NEXT",
    "TRANSITIONS",
    "UNCHANGED",
    "Transition",
    "TrackingEvent",
    "next_state",
    "transition",
]

_S = TrackingState
_R = StateReason


class TrackingEvent(enum.Enum):
    """What happened to the tracker: the input of the state table (not an app-facing event)."""

    FRAME_WITHOUT_MAP = "frame_without_map"  # a frame arrived and there is no map to track
    MAP_BUILT = "map_built"  # the first map (a bootstrap) was installed
    NEW_MAP_BUILT = "new_map_built"  # a new map after a timeout was installed
    # a new map after a timeout was installed from a frame only the relaxed floor let in
    RELAXED_MAP_BUILT = "relaxed_map_built"
    CONFIDENCE_LOST = "confidence_lost"  # confidence stayed low for ``lost_after`` frames
    CONFIDENCE_REGAINED = "confidence_regained"  # relocalised against the map
    TIMEOUT_STAY = "timeout_stay"  # relocalisation timed out; policy: keep trying
    TIMEOUT_RESET = "timeout_reset"  # relocalisation timed out; policy: drop the map, start over
    TIMEOUT_NEW_MAP = "timeout_new_map"  # relocalisation timed out; policy: build a new map
    MAP_LOADED = "map_loaded"  # a saved map was installed
    OBJECT_NOT_FOUND = "object_not_found"  # a loaded object map's object not found in time
    RESET = "reset"  # the app called reset()


_E = TrackingEvent

# (state, event) -> (next state, reason). The only place the tracker's life cycle is written; the
# order of first appearance of each (from, to) pair is the order of the drawn diagram.
NEXT: MappingProxyType[tuple[TrackingState, TrackingEvent], tuple[TrackingState, StateReason]] = (
    MappingProxyType(
        {
            # bootstrap: the first frame becomes keyframe 0 and the first map is built
            (_S.INIT, _E.FRAME_WITHOUT_MAP): (_S.MAPPING, _R.BOOTSTRAP),
            (_S.MAPPING, _E.MAP_BUILT): (_S.TRACKING, _R.BOOTSTRAP),
            (_S.MAPPING, _E.NEW_MAP_BUILT): (_S.TRACKING, _R.NEW_MAP),
            (_S.MAPPING, _E.RELAXED_MAP_BUILT): (_S.TRACKING, _R.RELAXED_FLOOR),
            # confidence-driven loss and recovery
            (_S.TRACKING, _E.CONFIDENCE_LOST): (_S.RELOCALIZING, _R.LOW_CONFIDENCE),
            (_S.TRACKING, _E.MAP_LOADED): (_S.RELOCALIZING, _R.MAP_LOADED),
            (_S.RELOCALIZING, _E.CONFIDENCE_REGAINED): (_S.TRACKING, _R.RELOCALIZED),
            # relocalisation timeout policies: stay (mark it), reset, start a new map
            # (and object mode: a loaded object map's object not found without a box)
            (_S.RELOCALIZING, _E.TIMEOUT_STAY): (_S.RELOCALIZING, _R.TIMEOUT),
            (_S.RELOCALIZING, _E.MAP_LOADED): (_S.RELOCALIZING, _R.MAP_LOADED),
            (_S.RELOCALIZING, _E.OBJECT_NOT_FOUND): (_S.RELOCALIZING, _R.OBJECT_NOT_FOUND),
            (_S.RELOCALIZING, _E.TIMEOUT_RESET): (_S.INIT, _R.TIMEOUT),
            (_S.RELOCALIZING, _E.RESET): (_S.INIT, _R.RESET),
            (_S.RELOCALIZING, _E.TIMEOUT_NEW_MAP): (_S.MAPPING, _R.NEW_MAP),
            # a saved map installed by the persistence layer
            (_S.INIT, _E.MAP_LOADED): (_S.RELOCALIZING, _R.MAP_LOADED),
            (_S.MAPPING, _E.MAP_LOADED): (_S.RELOCALIZING, _R.MAP_LOADED),
            # reset() from anywhere a map (or its bootstrap) exists
            (_S.MAPPING, _E.RESET): (_S.INIT, _R.RESET),
            (_S.TRACKING, _E.RESET): (_S.INIT, _R.RESET),
        }
    )
)

# events that change nothing in these states (no state-change event is sent)
UNCHANGED: frozenset[tuple[TrackingState, TrackingEvent]] = frozenset(
    {
        (_S.MAPPING, _E.FRAME_WITHOUT_MAP),  # the map is being built already
        (_S.INIT, _E.RESET),  # nothing to reset
    }
)


def _legal_moves() -> dict[tuple[TrackingState, TrackingState], frozenset[StateReason]]:
    moves: dict[tuple[TrackingState, TrackingState], set[StateReason]] = {}
    for (source, _), (target, reason) in NEXT.items():
        moves.setdefault((source, target), set()).add(reason)
    return {move: frozenset(reasons) for move, reasons in moves.items()}


# (from, to) -> reasons of the legal moves, derived from ``NEXT``
TRANSITIONS: MappingProxyType[tuple[TrackingState, TrackingState], frozenset[StateReason]] = (
    MappingProxyType(_legal_moves())
)


@dataclass(frozen=True)
class Transition:
    """A state change that the table allows."""

    previous: TrackingState
    state: TrackingState
    reason: StateReason


def next_state(current: TrackingState, event: TrackingEvent) -> Transition | None:
    """The move ``event`` causes in state ``current``; None when it changes nothing there.

    Pure: it changes nothing. Raises IllegalTransitionError when the table does not know the
    event in this state.
    """
    move = NEXT.get((current, event))
    if move is not None:
        return Transition(current, *move)
    if (current, event) in UNCHANGED:
        return None
    raise IllegalTransitionError(
        f"illegal event {event.value} in state {current.value} (no such move)"
    )


def transition(current: TrackingState, target: TrackingState, reason: StateReason) -> Transition:
    """Check ``current -> target`` with ``reason`` against the legal moves and return it.

    Pure: it changes nothing. Raises IllegalTransitionError (naming the move and the legal
    reasons, if any) when the table does not contain the move.
    """
    allowed = TRANSITIONS.get((current, target))
    if allowed is None or reason not in allowed:
        legal = sorted(r.value for r in allowed) if allowed else []
        raise IllegalTransitionError(
            f"illegal transition {current.value} -> {target.value} with reason {reason.value}"
            + (f" (legal reasons: {', '.join(legal)})" if legal else " (no such move)")
        )
    return Transition(current, target, reason)

"""The tracker's state machine: one table of legal transitions and a pure ``transition`` function.

Like ``h11/_state.py``: no I/O, no tracker knowledge, every legal move listed once. The ``Tracker``
facade is the only caller; anything not in the table is a bug and raises
:class:`~kvtracker_sdk.errors.IllegalTransitionError`.

The diagrams in ``docs/states.md`` and ``docs/architecture.md`` are drawn from this table by
``state_diagram.mermaid_state_diagram`` (a test compares them).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType

from kvtracker_sdk.errors import IllegalTransitionError
from kvtracker_sdk.types import StateReason, TrackingState

__all__ = ["TRANSITIONS", "Transition", "transition"]

_S = TrackingState
_R = StateReason

# (from, to) -> reasons allowed for that move. The only place the tracker's life cycle is written.
TRANSITIONS: MappingProxyType[tuple[TrackingState, TrackingState], frozenset[StateReason]] = (
    MappingProxyType(
        {
            # bootstrap: the first frame becomes keyframe 0 and the first map is built
            (_S.INIT, _S.MAPPING): frozenset({_R.BOOTSTRAP}),
            (_S.MAPPING, _S.TRACKING): frozenset({_R.BOOTSTRAP, _R.NEW_MAP, _R.RELAXED_FLOOR}),
            # confidence-driven loss and recovery
            (_S.TRACKING, _S.RELOCALIZING): frozenset({_R.LOW_CONFIDENCE, _R.MAP_LOADED}),
            (_S.RELOCALIZING, _S.TRACKING): frozenset({_R.RELOCALIZED}),
            # relocalisation timeout policies: stay (mark it), reset, start a new map
            # (and object mode: a loaded object map's object not found without a box)
            (_S.RELOCALIZING, _S.RELOCALIZING): frozenset(
                {_R.TIMEOUT, _R.MAP_LOADED, _R.OBJECT_NOT_FOUND}
            ),
            (_S.RELOCALIZING, _S.INIT): frozenset({_R.TIMEOUT, _R.RESET}),
            (_S.RELOCALIZING, _S.MAPPING): frozenset({_R.NEW_MAP}),
            # a saved map installed by the persistence layer
            (_S.INIT, _S.RELOCALIZING): frozenset({_R.MAP_LOADED}),
            (_S.MAPPING, _S.RELOCALIZING): frozenset({_R.MAP_LOADED}),
            # reset() from anywhere a map (or its bootstrap) exists
            (_S.MAPPING, _S.INIT): frozenset({_R.RESET}),
            (_S.TRACKING, _S.INIT): frozenset({_R.RESET}),
        }
    )
)


@dataclass(frozen=True)
class Transition:
    """A state change that the table allows."""

    previous: TrackingState
    state: TrackingState
    reason: StateReason


def transition(current: TrackingState, target: TrackingState, reason: StateReason) -> Transition:
    """Check ``current -> target`` with ``reason`` against the table and return it.

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

"""What the app hears about a finished mapping pass: the events of an accepted, rejected or failed
rebuild, and of a new world frame. Pure: it builds payloads; the ``Tracker`` posts them.
"""

from __future__ import annotations

from kvtracker_sdk.tracking.core.events import (
    BackendFailedEvent,
    Event,
    EventKind,
    KeyframeEvent,
    KeyframeRejectedEvent,
    MapUpdatedEvent,
    WorldFrameChangedEvent,
)
from kvtracker_sdk.tracking.mapping.failures import MappingFailure
from kvtracker_sdk.tracking.mapping.map_builder import RebuildOutcome
from kvtracker_sdk.types import StateReason

__all__ = ["WorldFrameChange", "failure_event", "rebuild_events"]

# why a world frame ended and the generation of its last map; reported with the next map
WorldFrameChange = tuple[StateReason, int]


def failure_event(failure: MappingFailure) -> tuple[EventKind, Event]:
    """The one event of a failed mapping pass."""
    error = failure.error
    return EventKind.BACKEND_FAILED, BackendFailedEvent(
        "map", failure.request.candidate.frame_index, str(error), error, failure.consecutive,
        failure.retry_at_frame,
    )


def rebuild_events(
    outcome: RebuildOutcome, rejection_ratio: float, world_change: WorldFrameChange | None
) -> list[tuple[EventKind, Event]]:
    """The events of a taken rebuild, in order. ``world_change``: set when the previous world frame
    was dropped; an accepted bootstrap then opens the new one."""
    new_map, request = outcome.new_map, outcome.request
    candidate = new_map.keyframes[-1]
    if not outcome.accepted:
        # a floored bootstrap (a new map after a loss) is judged against an absolute floor: ratio 1
        floored = request.previous is None and request.min_confidence is not None
        return [(EventKind.KEYFRAME_REJECTED, KeyframeRejectedEvent(
            candidate.keyframe_id, candidate.frame_index, outcome.candidate_confidence,
            outcome.reference_confidence, 1.0 if floored else rejection_ratio))]
    events: list[tuple[EventKind, Event]] = [
        (EventKind.KEYFRAME, KeyframeEvent.of(candidate, new_map.generation)),
        (EventKind.MAP_UPDATED, MapUpdatedEvent.of(
            new_map, request.cause.value, request.evicted, outcome.correction)),
    ]
    if request.previous is None and world_change is not None:
        reason, previous_generation = world_change
        events.append((EventKind.WORLD_FRAME_CHANGED, WorldFrameChangedEvent(
            reason, previous_generation, new_map.generation, candidate.frame_index)))
    return events

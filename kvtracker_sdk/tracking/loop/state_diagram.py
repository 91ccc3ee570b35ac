"""The state machine drawn from its table: the mermaid diagram in ``docs/states.md`` and
``docs/architecture.md`` is this function's output (``tests/test_state_diagrams.py`` fails when a
drawing and the table in ``states.py`` drift apart).

One arrow per (from, to) pair of ``TRANSITIONS``, in the table's order, labelled with its reasons
in ``StateReason`` order; ``[*] --> INIT`` marks where every tracker starts.
"""

from __future__ import annotations

from kvtracker_sdk.tracking.loop.states import TRANSITIONS
from kvtracker_sdk.types import StateReason, TrackingState

__all__ = ["mermaid_state_diagram"]


def mermaid_state_diagram() -> str:
    """The ``stateDiagram-v2`` text (no code fence), lines ending in ``\\n``."""
    order = list(StateReason)
    lines = ["stateDiagram-v2", f"    [*] --> {TrackingState.INIT.value}"]
    for (source, target), reasons in TRANSITIONS.items():
        label = " / ".join(reason.value for reason in sorted(reasons, key=order.index))
        lines.append(f"    {source.value} --> {target.value}: {label}")
    return "\n".join(lines) + "\n"

"""The rebuild cycle drawn from its table: the mermaid diagram of the map-rebuild cycle in
``docs/states.md`` is this function's output (``tests/test_state_diagrams.py`` fails when the
drawing and ``rebuild_cycle.MOVES`` drift apart).

One arrow per (from, to) pair of ``MOVES``, in the table's order, labelled with its events in
``RebuildEvent`` order; ``[*] --> IDLE`` marks where every keeper starts.
"""

from __future__ import annotations

from kvtracker_sdk.tracking.mapping.rebuild_cycle import MOVES, RebuildEvent, RebuildPhase

__all__ = ["mermaid_rebuild_diagram"]


def mermaid_rebuild_diagram() -> str:
    """The ``stateDiagram-v2`` text (no code fence), lines ending in ``\\n``."""
    arrows: dict[tuple[RebuildPhase, RebuildPhase], set[RebuildEvent]] = {}
    for (source, event), targets in MOVES.items():
        for target in sorted(targets, key=list(RebuildPhase).index):
            arrows.setdefault((source, target), set()).add(event)
    order = list(RebuildEvent)
    lines = ["stateDiagram-v2", f"    [*] --> {RebuildPhase.IDLE.value}"]
    for (source, target), events in arrows.items():
        label = " / ".join(event.value for event in sorted(events, key=order.index))
        lines.append(f"    {source.value} --> {target.value}: {label}")
    return "\n".join(lines) + "\n"

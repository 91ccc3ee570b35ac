"""The state diagrams of the states guide and the architecture notes are drawn from their tables:
the tracker's (``tracking.loop.state_diagram`` from ``tracking/loop/states.py``) and the map
keeper's rebuild cycle (``tracking.mapping.rebuild_diagram`` from
``tracking/mapping/rebuild_cycle.py``). A drawing that drifts from its table fails here."""

from __future__ import annotations

import re

import pytest

from kvtracker_sdk.tracking.loop.state_diagram import mermaid_state_diagram
from kvtracker_sdk.tracking.loop.states import TRANSITIONS
from kvtracker_sdk.tracking.mapping.rebuild_cycle import MOVES
from kvtracker_sdk.tracking.mapping.rebuild_diagram import mermaid_rebuild_diagram
from tests.helpers import PROJECT_ROOT

FENCE = re.compile(r"```mermaid\n(stateDiagram-v2\n.*?)```", re.DOTALL)


def _drawn(document: str, start: str) -> list[str]:
    """The document's mermaid state diagrams that start at ``start`` (``[*] --> start``)."""
    blocks = FENCE.findall((PROJECT_ROOT / document).read_text(encoding="utf-8"))
    return [b for b in blocks if b.splitlines()[1].strip() == f"[*] --> {start}"]


@pytest.mark.parametrize(
    ("document", "start", "draw"),
    [
        ("docs/states.md", "INIT", mermaid_state_diagram),
        ("docs/architecture.md", "INIT", mermaid_state_diagram),
        ("docs/states.md", "IDLE", mermaid_rebuild_diagram),
    ],
)
def test_the_drawn_state_machine_is_the_table(document: str, start: str, draw) -> None:
    blocks = _drawn(document, start)
    assert len(blocks) == 1, f"{document}: expected one mermaid diagram starting at {start}"
    expected = draw()
    assert blocks[0] == expected, (
        f"{document} drifted from its table; replace its diagram with:\n{expected}"
    )


def test_every_legal_move_is_drawn_once() -> None:
    arrows = [line for line in mermaid_state_diagram().splitlines() if "-->" in line][1:]
    assert len(arrows) == len(TRANSITIONS)
    for (source, target), reasons in TRANSITIONS.items():
        (line,) = [a for a in arrows if a.split(":")[0].split() == [source.value, "-->", target.value]]
        assert set(line.split(": ")[1].split(" / ")) == {reason.value for reason in reasons}


def test_every_rebuild_move_is_drawn_once() -> None:
    arrows = [line for line in mermaid_rebuild_diagram().splitlines() if "-->" in line][1:]
    drawn = {
        (a.split(":")[0].split()[0], a.split(":")[0].split()[2], event)
        for a in arrows
        for event in a.split(": ")[1].split(" / ")
    }
    table = {
        (source.value, target.value, event.value)
        for (source, event), targets in MOVES.items()
        for target in targets
    }
    assert drawn == table
    assert len(arrows) == len({(s, t) for s, t, _ in table})

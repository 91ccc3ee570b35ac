"""The state diagrams of the states guide and the architecture notes are drawn from the
transition table (``tracking.loop.state_diagram``): a drawing that drifts from ``tracking/loop/states.py`` fails here."""

from __future__ import annotations

import re

import pytest

from kvtracker_sdk.tracking.loop.state_diagram import mermaid_state_diagram
from kvtracker_sdk.tracking.loop.states import TRANSITIONS
from tests.helpers import PROJECT_ROOT

FENCE = re.compile(r"```mermaid\n(stateDiagram-v2\n.*?)```", re.DOTALL)


@pytest.mark.parametrize("document", ["docs/states.md", "docs/architecture.md"])
def test_the_drawn_state_machine_is_the_table(document: str) -> None:
    blocks = FENCE.findall((PROJECT_ROOT / document).read_text(encoding="utf-8"))
    assert len(blocks) == 1, f"{document}: expected one mermaid state diagram"
    expected = mermaid_state_diagram()
    assert blocks[0] == expected, (
        f"{document} drifted from tracking/loop/states.py; replace its diagram with:\n{expected}"
    )


def test_every_legal_move_is_drawn_once() -> None:
    arrows = [line for line in mermaid_state_diagram().splitlines() if "-->" in line][1:]
    assert len(arrows) == len(TRANSITIONS)
    for (source, target), reasons in TRANSITIONS.items():
        (line,) = [a for a in arrows if a.split(":")[0].split() == [source.value, "-->", target.value]]
        assert set(line.split(": ")[1].split(" / ")) == {reason.value for reason in reasons}

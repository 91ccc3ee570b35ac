"""The object keyframe rules' table (the orbit table): the numbers the benchmarks README and the object guide show."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.object_keyframe_rules import main, table
from tests.helpers import PROJECT_ROOT


def test_the_view_direction_rule_covers_rings_poles_and_revisits(tmp_path: Path) -> None:
    measured = main(["--out", str(tmp_path / "r.json")])
    for document in ("benchmarks/README.md", "docs/object_tracking.md"):  # the tables shown are these
        assert table(measured, 10.0) in (PROJECT_ROOT / document).read_text()
    rows = {(r.path.split(" (")[0], r.rule): r for r in measured}
    view, paper = "view_direction", "azimuth_elevation"
    assert rows["one ring", view].keyframes == rows["one ring", paper].keyframes == 34
    # a second ring 30 deg higher: about 360 / tau new keyframes (cos 30 deg of the ring's length)
    assert 28 <= rows["two rings", view].added_in_second_part <= 36
    assert rows["two rings", paper].added_in_second_part <= 1  # the step up, then nothing
    assert rows["two rings", paper].coverage < 0.6 and rows["two rings", view].coverage == 1.0
    # the orbit at 85 deg: all views within 10 deg of each other
    assert rows["orbit at 85 deg", view].keyframes <= 2
    assert rows["orbit at 85 deg", paper].keyframes >= 30
    assert rows["revisit", view].added_in_second_part == 0
    assert rows["revisit", paper].added_in_second_part == 0
    saved = json.loads((tmp_path / "r.json").read_text())
    assert saved["tau_deg"] == 10.0 and len(saved["rows"]) == 8

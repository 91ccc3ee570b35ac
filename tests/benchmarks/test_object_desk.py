"""The issue's "Done when" on the full runs of ``benchmarks/object_desk.py`` (slow: ~10 CPU-s per
layout): the 720-frame walk on the desk and against the wall from one box with a 1.5 s loss, and
the saved map found again in a *new process* with no box."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.object_desk import first_walk, layout, reload_in_new_process


@pytest.mark.slow
@pytest.mark.parametrize("name", ["desk", "wall"])
def test_done_when_on_the_full_walk_and_reload(name: str, tmp_path: Path) -> None:
    path = tmp_path / f"{name}.kvmap"
    first = first_walk(layout(name), path)
    assert first["tracked"] >= 0.85 * first["frames"]  # the loss and the object at the border
    assert first["iou_ok"] >= 0.95  # measured: desk 97.9 %, wall 99.1 %
    assert first["within_1cm"] >= 0.9  # measured: 100 %
    assert first["origin_error_of_radius"] <= 0.1  # measured: desk 2.1 %, wall 8.1 %
    assert max(first["extent_error_per_axis"]) <= 0.15  # measured: <= 5 %, <= 7 %
    assert first["has_up"]
    again = reload_in_new_process(name, path, frames=120)  # the object is in view at ~30
    assert again["mode"] == "object" and again["sources_before"] == []
    assert 0 <= again["frames_to_find"] <= 10  # measured: 2
    assert again["iou_ok"] >= 0.95  # measured: 100 %

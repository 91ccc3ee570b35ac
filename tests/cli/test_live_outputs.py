"""``--view`` and ``--ros2-bag`` on ``kvtracker demo``: the bag reads back with every topic, the
view serves on loopback, and without their extras the run still writes its other outputs."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from tests.cli.invoke import invoke
from tests.helpers import dev_dependency

DEMO = ("demo", "--frames", "45", "--size", "120x160", "--keyframe-interval", "20")


def test_demo_writes_a_bag_with_every_topic_and_serves_the_view(tmp_path: Path) -> None:
    dev_dependency("viser")
    dev_dependency("rosbags")
    from rosbags.highlevel import AnyReader

    from kvtracker_sdk.io.exports.ros2_bag import TOPICS

    result = invoke(*DEMO, "--out", tmp_path / "run", "--ros2-bag", tmp_path / "bag",
                    "--view", "--view-port", "0")
    assert result.exit_code == 0, result.output
    assert "live view  http://127.0.0.1:" in result.stderr
    with AnyReader([tmp_path / "bag"]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert {c.topic: c.msgtype for c in reader.connections} == TOPICS
    assert counts["/diagnostics"] == counts["/camera/camera_info"] == 45
    assert all(counts.values())
    assert (tmp_path / "run" / "run.json").is_file()


def test_without_viser_the_run_goes_on_without_the_view(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "viser", None)  # import viser -> ImportError
    result = invoke(*DEMO, "--out", tmp_path, "--view", "--view-port", "0")
    assert result.exit_code == 0, result.output
    assert 'pip install -e ".[view]"' in result.stderr
    assert (tmp_path / "run.json").is_file()


def test_without_rosbags_the_other_outputs_are_written_and_the_exit_code_says_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    for module in ("rosbags", "rosbags.rosbag2", "rosbags.typesys"):
        monkeypatch.setitem(sys.modules, module, None)
    result = invoke(*DEMO, "--out", tmp_path / "run", "--ros2-bag", tmp_path / "bag")
    assert result.exit_code == 5, result.output
    assert 'pip install -e ".[ros]"' in result.stderr
    assert {"trajectory.txt", "points.ply", "run.json"} <= {p.name for p in (tmp_path / "run").iterdir()}
    assert not (tmp_path / "bag").exists()


def test_an_interrupted_run_keeps_its_bag(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    dev_dependency("rosbags")
    from rosbags.highlevel import AnyReader

    from kvtracker_sdk.tracking.facade.tracker import Tracker

    push = Tracker.push_frame
    pushed = []

    def interrupting(self: Tracker, *args: object, **kwargs: object) -> object:
        if len(pushed) == 30:
            raise KeyboardInterrupt  # Ctrl-C while tracking frame 30
        pushed.append(1)
        return push(self, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(Tracker, "push_frame", interrupting)
    result = invoke(*DEMO, "--out", tmp_path / "run", "--ros2-bag", tmp_path / "bag")
    assert result.exit_code == 130, result.output
    with AnyReader([tmp_path / "bag"]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts["/diagnostics"] == 30 and counts["/kvtracker/map_points"] >= 1

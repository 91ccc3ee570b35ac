"""Numbers on the command line are checked before anything starts (a port of 70000 or -1 used
to hang ``--view`` forever), and ``demo --gt`` refuses a ground truth that would need billions of
frames (two poses far apart in time grew to 24 GB before the kernel killed it)."""

from __future__ import annotations

from pathlib import Path

import pytest

from kvtracker_sdk.backends.simulated_scene import MAX_FRAMES
from tests.cli.invoke import invoke


@pytest.mark.parametrize("command", ["demo", "track"])
@pytest.mark.parametrize("port", ["70000", "-1", "65536"])
def test_an_impossible_view_port_is_a_usage_error(tmp_path: Path, command: str, port: str) -> None:
    source = [] if command == "demo" else [str(tmp_path)]
    result = invoke(command, *source, "--view", "--view-port", port, "--out", tmp_path / "out")
    assert result.exit_code == 2
    assert "view-port" in result.output
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("option", "value"),
    [("--frames", "0"), ("--frames", str(10**9)), ("--noise-cm", "nan"), ("--noise-deg", "inf"),
     ("--keyframe-interval", "0"), ("--seed", "-1")],
)
def test_impossible_demo_numbers_are_usage_errors(tmp_path: Path, option: str, value: str) -> None:
    result = invoke("demo", option, value, "--out", tmp_path / "out")
    assert result.exit_code == 2 and option in result.output


def test_demo_refuses_a_ground_truth_spanning_years(tmp_path: Path) -> None:
    gt = tmp_path / "groundtruth.txt"
    gt.write_text("0 0 0 0 0 0 0 1\n100000000 1 0 0 0 0 0 1\n")
    result = invoke("demo", "--gt", gt, "--out", tmp_path / "out")
    assert result.exit_code != 0 and "time span" in result.output


def test_the_cli_frame_limit_is_the_simulators() -> None:
    from kvtracker_sdk.cli.number_options import MAX_SIMULATED_FRAMES

    assert MAX_SIMULATED_FRAMES == MAX_FRAMES

"""The frame loop: what it records, and a Ctrl-C that still leaves a complete output folder."""

from __future__ import annotations

import json
import signal
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from rich.console import Console

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.cli.failures import ExitCode
from kvtracker_sdk.cli.logging_setup import CliState
from kvtracker_sdk.cli.outputs import RunDescription
from kvtracker_sdk.cli.progress import FrameProgress
from kvtracker_sdk.cli.session import OutputOptions, run_session
from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.runs.run_loop import InputFrame, run_frames
from kvtracker_sdk.tracking.facade.tracker import Tracker

SIZE = (196, 252)  # the model resolution of d = 224 for 4:3 frames: no resize


def frames(backend: SimulatedBackend, count: int, interrupt_at: int | None = None
           ) -> Iterator[InputFrame]:
    for frame in backend.frames(SIZE, stop=count, textured=False):
        if frame.index == interrupt_at:
            raise KeyboardInterrupt
        yield InputFrame(frame.image, frame.timestamp)


def test_record_counts_states_stages_and_valid_poses() -> None:
    backend = SimulatedBackend(orbit(60), loss_segments=[(20, 35)])
    progress = FrameProgress(Console(force_terminal=False), 60, label="t")
    with Tracker(TrackerConfig(resolution=224), backend) as tracker:
        record = run_frames(tracker, frames(backend, 60), progress)
    assert record.num_frames == 60 and not record.interrupted
    assert record.states_visited() == ["INIT", "MAPPING", "TRACKING", "RELOCALIZING", "TRACKING"]
    per_state = record.frames_per_state()
    assert sum(per_state.values()) == 60 and per_state["RELOCALIZING"] > 10
    trajectory = record.trajectory()
    assert len(trajectory) == sum(r.pose_valid for r in record.results) < 60
    np.testing.assert_array_equal(trajectory.stamps[:3], np.arange(3) / 30.0)
    stats = record.stage_stats()
    assert stats["source"].count == 60 and stats["track"].count == 59  # frame 0 maps, not tracks
    assert stats["map"].count == 2  # the bootstrap and the keyframe at frame 50 (interval 50)
    assert stats["map"].p95_ms >= stats["map"].mean_ms * 0.999


def test_ctrl_c_writes_the_outputs_of_the_frames_processed(tmp_path: Path) -> None:
    backend = SimulatedBackend(orbit(40))
    state = CliState(verbosity=-1, console=Console(force_terminal=False))
    with Tracker(TrackerConfig(resolution=224), backend) as tracker:
        try:
            run_session(state, tracker, frames(backend, 40, interrupt_at=25), total=40,
                        description=RunDescription("track", "test", simulated=True),
                        options=OutputOptions(tmp_path))
        except Exception as exit_:  # typer.Exit
            assert getattr(exit_, "exit_code", None) == ExitCode.INTERRUPTED
        else:
            raise AssertionError("an interrupted run must exit with 130")
    run = json.loads((tmp_path / "run.json").read_text())
    assert run["interrupted"] is True and run["frames"] == 25
    assert (tmp_path / "trajectory.txt").read_text().count("\n") == 25 + 1  # header + 25 poses


def test_a_first_ctrl_c_lets_the_current_frame_finish() -> None:
    """SIGINT while frame 12 is being read: the loop stops before tracking another frame, not
    in the middle of one, and the previous handler is back afterwards."""
    backend = SimulatedBackend(orbit(40))
    before = signal.getsignal(signal.SIGINT)

    def interrupted(count: int) -> Iterator[InputFrame]:
        for frame in frames(backend, count):
            if len(seen) == 12:
                signal.raise_signal(signal.SIGINT)  # handled at once, on this (main) thread
            seen.append(frame.timestamp)
            yield frame

    seen: list[float] = []
    progress = FrameProgress(Console(force_terminal=False), 40, label="t")
    with Tracker(TrackerConfig(resolution=224), backend) as tracker:
        record = run_frames(tracker, interrupted(40), progress)
        assert tracker.state.value == "TRACKING"
    assert record.interrupted and record.num_frames == 12 and record.failure is None
    assert signal.getsignal(signal.SIGINT) is before

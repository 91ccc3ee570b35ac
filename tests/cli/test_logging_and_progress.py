"""Logging is configured by the CLI only: readable lines, JSON lines, levels; no handler stacking."""

from __future__ import annotations

import json
import logging
from pathlib import Path

from rich.console import Console

from kvtracker_sdk.cli.logging_setup import CliState, configure_logging, level_for
from kvtracker_sdk.cli.progress import FrameProgress
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.types import FrameResult, StateReason, TrackingState
from tests.cli.invoke import invoke

DEMO = ("demo", "--frames", "12", "--size", "60x80", "--resolution", "224")


def test_log_json_writes_one_json_object_per_stderr_line(tmp_path: Path) -> None:
    result = invoke("--log-json", "-v", *DEMO, "--out", tmp_path)
    assert result.exit_code == 0, result.output
    records = [json.loads(line) for line in result.stderr.splitlines()]  # every line parses
    events = [r["event"] for r in records]
    assert "state_change" in events and events[-1] == "run finished"
    finished = records[-1]
    assert finished["simulated"] is True and finished["frames"] == 12
    assert {"level", "timestamp", "logger"} <= set(finished)
    # the human notes (state prints, notice) become log events, not free text on stderr
    assert any(r["event"] == "simulated run" for r in records)
    assert "kvtracker demo" in result.stdout  # the summary stays on stdout


def test_default_is_quiet_below_warning_and_v_shows_events(tmp_path: Path) -> None:
    plain = invoke(*DEMO, "--out", tmp_path / "a")
    verbose = invoke("-v", *DEMO, "--out", tmp_path / "b")
    assert plain.exit_code == verbose.exit_code == 0
    assert "state_change" not in plain.stderr
    assert "state_change" in verbose.stderr and "reason=BOOTSTRAP" in verbose.stderr


def test_quiet_prints_nothing_on_success(tmp_path: Path) -> None:
    result = invoke("-q", *DEMO, "--out", tmp_path)
    assert result.exit_code == 0 and result.stdout == "" and result.stderr == ""
    assert (tmp_path / "run.json").is_file()


def test_configure_logging_replaces_its_handler() -> None:
    logger = logging.getLogger("kvtracker_sdk")
    before = list(logger.handlers)
    try:
        for verbosity in (0, 2, -1):
            configure_logging(CliState(verbosity=verbosity))
        ours = [h for h in logger.handlers if h.get_name() == "kvtracker-cli"]
        assert len(ours) == 1 and logger.level == logging.ERROR
    finally:
        for handler in [h for h in logger.handlers if h not in before]:
            logger.removeHandler(handler)
        logger.setLevel(logging.NOTSET)
        logger.propagate = True
    assert level_for(1) == logging.INFO and level_for(5) == logging.DEBUG


def test_readable_lines_carry_the_key_values() -> None:
    console = Console(record=True, width=200, force_terminal=False)
    logger = logging.getLogger("kvtracker_sdk")
    try:
        configure_logging(CliState(verbosity=1, console=console))
        get_logger("tests.cli").info("keyframe", keyframe_id=7, frame_index=42)
    finally:
        for handler in [h for h in logger.handlers if h.get_name() == "kvtracker-cli"]:
            logger.removeHandler(handler)
        logger.setLevel(logging.NOTSET)
        logger.propagate = True
    text = console.export_text()
    assert "keyframe" in text and "keyframe_id=7" in text and "frame_index=42" in text


def test_progress_reports_fps_and_is_off_without_a_terminal() -> None:
    result = FrameResult(
        frame_index=0, timestamp=0.0, state=TrackingState.TRACKING, reason=StateReason.NONE,
        pose=None, pose_valid=False, confidence=None,
    )
    quiet = FrameProgress(Console(force_terminal=False), 10, label="t")
    assert not quiet.enabled
    live = FrameProgress(Console(force_terminal=True, record=True, width=120), 10, label="t")
    with live:
        for _ in range(5):
            live.update(result, num_keyframes=1)
    assert live.enabled and live.fps > 0

"""Errors: one ``error:`` line, a ``hint:`` line, and the documented exit code."""

from __future__ import annotations

from pathlib import Path

import pytest

from kvtracker_sdk import errors
from kvtracker_sdk.cli.failures import EXIT_CODES, EXIT_CODES_EPILOG, ExitCode, exit_code_for
from tests.cli.invoke import invoke
from tests.helpers import shared_path


def _error_lines(output: str) -> list[str]:
    return [line for line in output.splitlines() if line.startswith(("error:", "hint:"))]


def test_every_exit_code_is_documented_in_help() -> None:
    assert set(EXIT_CODES) == {int(code) for code in ExitCode}
    for command in ([], ["track"], ["demo"], ["eval"], ["map", "info"]):
        result = invoke(*command, "--help")
        assert result.exit_code == 0
        flat = " ".join(result.stdout.replace("│", " ").split())
        assert "Exit codes: 0 success" in flat and "130 interrupted" in flat, command
    assert all(f"{int(code)} " in EXIT_CODES_EPILOG for code in ExitCode)


@pytest.mark.parametrize(
    ("error", "code"),
    [
        (errors.WeightsNotFoundError("x"), ExitCode.WEIGHTS),  # before OSError and ModelError
        (errors.CheckpointMismatchError("x"), ExitCode.WEIGHTS),
        (errors.MissingDependencyError("x"), ExitCode.DEPENDENCY),  # before BackendError
        (errors.EvaluationError("x"), ExitCode.EVALUATION),  # before InputError
        (errors.SourceError("x"), ExitCode.INPUT),
        (errors.SourceOpenError("x"), ExitCode.SOURCE),  # before SourceError
        (errors.MaskError("x"), ExitCode.INPUT),
        (errors.MapIOError("x"), ExitCode.MAP),  # before OSError
        (errors.MapModelMismatchError("x"), ExitCode.MAP),
        (errors.ConfigError("x"), ExitCode.CONFIG),
        (errors.BackendMismatchError("x"), ExitCode.BACKEND),
        (PermissionError("x"), ExitCode.OUTPUT),
        (RuntimeError("x"), ExitCode.INTERNAL),
    ],
)
def test_the_most_specific_exit_code_wins(error: Exception, code: ExitCode) -> None:
    assert exit_code_for(error)[0] is code


def test_missing_weights_offline_says_how_to_pass_a_local_file(tmp_path: Path) -> None:
    tum = shared_path("data", "tum_fr2_desk")
    result = invoke("track", tum, "--out", tmp_path, "--weights", tmp_path / "missing.safetensors")
    assert result.exit_code == ExitCode.WEIGHTS
    error, hint = _error_lines(result.stderr)
    assert "missing.safetensors" in error
    assert "--weights /path/to/model.safetensors" in hint
    assert "Traceback" not in result.stderr  # tracebacks only with -v


def test_verbose_errors_show_the_traceback(tmp_path: Path) -> None:
    result = invoke("-v", "track", tmp_path / "nowhere", "--out", tmp_path)
    assert result.exit_code == ExitCode.SOURCE
    assert "Traceback" in result.stderr and "SourceOpenError" in result.stderr


@pytest.mark.parametrize(
    ("args", "code", "needle"),
    [
        (["track", "{tmp}/nowhere"], ExitCode.SOURCE, "does not exist"),
        (["track", "{tum}", "--resolution", "100"], ExitCode.CONFIG, "resolution"),
        (["track", "{tum}", "--bbox", "1,2,3"], ExitCode.INPUT, "four numbers"),
        (["track", "{tum}", "--masks", "{tmp}/nowhere", "--mode", "object"], ExitCode.INPUT,
         "mask folder"),
        (["track", "{tum}", "--config", "{tmp}/nowhere.json"], ExitCode.CONFIG, "--config"),
        (["demo", "--size", "10x10"], ExitCode.CONFIG, "28 pixels"),
        (["demo", "--loss", "9:3"], ExitCode.CONFIG, "START < STOP"),
        (["eval", "{tum}/rgb.txt", "{tum}/groundtruth.txt"], ExitCode.INPUT, "rgb.txt"),
        (["eval", "{tmp}/est.txt", "{tum}/groundtruth.txt"], ExitCode.EVALUATION, "no timestamps"),
        (["eval", "{tmp}/est.txt", "{tmp}/est.txt", "--cm-deg", "x"], ExitCode.CONFIG, "1,3,5"),
        (["map", "info", "{tum}/rgb.txt"], ExitCode.MAP, "not a kvtracker map"),
        (["map", "info", "{tmp}/nowhere.kvmap"], ExitCode.MAP, "nowhere.kvmap"),
    ],
)
def test_bad_input_exit_codes(args: list[str], code: ExitCode, needle: str, tmp_path: Path) -> None:
    tum = shared_path("data", "tum_fr2_desk")
    (tmp_path / "est.txt").write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 1 0 0 0 1\n3.0 1 0 1 0 0 0 1\n")
    filled = [a.format(tmp=tmp_path, tum=tum) for a in args]
    result = invoke(*filled, "--out", tmp_path / "out") if args[0] in ("track", "demo") else invoke(
        *filled
    )
    assert result.exit_code == code, result.output
    error, hint = _error_lines(result.stderr)
    assert needle in error and hint.startswith("hint: ")


def test_object_mode_without_masks_is_refused_before_tracking(tmp_path: Path,
                                                              golden_weights: Path) -> None:
    tum = shared_path("data", "tum_fr2_desk")
    result = invoke("track", tum, "--weights", golden_weights, "--mode", "object",
                    "--out", tmp_path)
    assert result.exit_code == ExitCode.CONFIG
    assert "--masks DIR or --bbox" in result.stderr
    assert not (tmp_path / "run.json").exists()


def test_usage_errors_keep_click_exit_code_2() -> None:
    result = invoke("track", "--no-such-option")
    assert result.exit_code == ExitCode.USAGE

"""The end of a run keeps the user's work: without the [viz] extra, after a bad frame, after
Ctrl-C; and output locations are checked before the first frame.

In-process runs use the simulated backend over PNG frames of its orbit (``simulated_frames``,
``simulated_backend`` in conftest.py); the one subprocess test uses the tiny golden Pi3.
"""

from __future__ import annotations

import json
import os
import queue
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from kvtracker_sdk.cli.failures import EXIT_CODES, ExitCode
from kvtracker_sdk.io.files.trajectory import read_tum
from tests.cli.conftest import SIMULATED_FRAMES
from tests.cli.invoke import invoke
from tests.helpers import PROJECT_ROOT, shared_path

SMALL_DEMO = ("--frames", "40", "--size", "60x80", "--resolution", "224")
TRACK = ("--resolution", "224", "--keyframe-interval", "5")
NON_PLOT_OUTPUTS = {"trajectory.txt", "keyframes.json", "points.ply", "run.json",
                    "groundtruth.txt", "evaluation.json"}


@pytest.fixture
def no_viz_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    """``import matplotlib`` and ``import rerun`` (and every submodule) fail, as without the
    [viz] extra: a None in ``sys.modules`` makes an import raise ImportError."""
    for package in ("matplotlib", "rerun"):
        for name in [n for n in sys.modules if n == package or n.startswith(package + ".")]:
            monkeypatch.setitem(sys.modules, name, None)
        monkeypatch.setitem(sys.modules, package, None)


def copy_frames(source: Path, target: Path) -> Path:
    target.mkdir()
    for path in sorted(source.iterdir()):
        (target / path.name).write_bytes(path.read_bytes())
    return target


# ----------------------------------------------------------------------------- 13: no [viz]
@pytest.mark.usefixtures("no_viz_extra")
def test_demo_without_the_viz_extra_writes_every_non_plot_output(tmp_path: Path) -> None:
    result = invoke("demo", "--out", tmp_path, *SMALL_DEMO)
    assert result.exit_code == 0, result.output
    names = {p.name for p in tmp_path.iterdir()}
    assert names >= NON_PLOT_OUTPUTS and "trajectory.png" not in names
    run = json.loads((tmp_path / "run.json").read_text())
    assert 'pip install -e ".[viz]"' in run["skipped_outputs"]["trajectory.png"]
    assert "trajectory.png not written" in result.stdout  # the summary says what is missing
    assert "trajectory.png not written" in result.stderr  # and a warning is logged


@pytest.mark.usefixtures("no_viz_extra", "simulated_backend")
def test_track_without_the_viz_extra_saves_the_map(tmp_path: Path, simulated_frames: Path) -> None:
    from kvtracker_sdk import read_map_info

    out, saved = tmp_path / "out", tmp_path / "scene.kvmap"
    result = invoke("track", simulated_frames, "--out", out, *TRACK, "--save-map", saved)
    assert result.exit_code == 0, result.output
    run = json.loads((out / "run.json").read_text())
    assert read_map_info(saved).num_keyframes == run["map"]["keyframes"] >= 2
    assert run["outputs"]["map"] == str(saved) and "trajectory.png" in run["skipped_outputs"]
    # eval prints its numbers too; only its plot is missing
    (out / "copy.txt").write_bytes((out / "trajectory.txt").read_bytes())
    scored = invoke("eval", out / "trajectory.txt", out / "copy.txt")
    assert scored.exit_code == 0 and "ATE  RMSE" in scored.stdout, scored.output


# ----------------------------------------------------------------------------- 14: bad frames
@pytest.mark.usefixtures("simulated_backend")
def test_a_bad_frame_stops_the_run_and_keeps_what_was_tracked(
    tmp_path: Path, simulated_frames: Path
) -> None:
    from kvtracker_sdk import read_map_info

    frames = copy_frames(simulated_frames, tmp_path / "frames")
    (frames / "016.png").write_bytes(b"not a png")  # e.g. a file cut short by a full disk
    out, saved = tmp_path / "out", tmp_path / "m.kvmap"
    result = invoke("track", frames, "--out", out, *TRACK, "--save-map", saved)
    assert result.exit_code == ExitCode.INPUT, result.output
    assert "016.png: cannot decode" in result.stderr
    run = json.loads((out / "run.json").read_text())
    assert run["frames"] == 16 and run["valid_poses"] == 16
    assert run["stopped_by"].startswith("FrameDecodeError") and run["bad_frames"]["count"] == 1
    assert len(read_tum(out / "trajectory.txt")) == 16
    assert read_map_info(saved).num_keyframes == run["map"]["keyframes"] >= 2


@pytest.mark.usefixtures("simulated_backend")
def test_bad_frames_can_be_skipped_counted_and_reported(
    tmp_path: Path, simulated_frames: Path
) -> None:
    frames = copy_frames(simulated_frames, tmp_path / "frames")
    (frames / "016.png").write_bytes(b"not a png")
    cv2.imwrite(str(frames / "008.png"), np.zeros((50, 60, 3), np.uint8))  # another size
    out = tmp_path / "out"
    result = invoke("track", frames, "--out", out, *TRACK, "--on-bad-frame", "skip")
    assert result.exit_code == 0, result.output
    run = json.loads((out / "run.json").read_text())
    assert run["frames"] == SIMULATED_FRAMES - 2 and run["stopped_by"] is None
    bad = run["bad_frames"]
    assert bad["policy"] == "skip" and bad["count"] == 2
    assert [b["position"] for b in bad["frames"]] == [8, 16]
    assert "size" in bad["frames"][0]["error"] and "cannot decode" in bad["frames"][1]["error"]
    assert "bad frames 2 skipped" in result.stdout
    stamps = read_tum(out / "trajectory.txt").stamps
    assert 8 / 30 not in stamps.tolist() and len(stamps) == run["valid_poses"]


# ----------------------------------------------------------------------------- 14: Ctrl-C
def _lines(stream: Iterator[str], into: queue.Queue[str]) -> None:
    for line in stream:
        into.put(line)
    into.put("")  # end of stream


@pytest.mark.slow
def test_sigint_saves_the_map_with_the_keyframes_made_so_far(tmp_path: Path,
                                                              golden_weights: Path) -> None:
    """A real ``kvtracker track`` process, interrupted once it has made two keyframes."""
    from kvtracker_sdk import read_map_info

    tum = shared_path("data", "tum_fr2_desk", "rgb")
    images = sorted(tum.iterdir())
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(400):  # far more than the run gets through before it is interrupted
        (frames / f"{k:04d}.png").symlink_to(images[k % len(images)])
    out, saved = tmp_path / "out", tmp_path / "desk.kvmap"
    command = [sys.executable, "-m", "kvtracker_sdk.cli", "-v", "--log-json", "track", str(frames),
               "--weights", str(golden_weights), "--out", str(out), "--save-map", str(saved),
               "--resolution", "224", "--threads", "1", "--keyframe-interval", "2"]
    env = {**os.environ, "PYTHONPATH": str(PROJECT_ROOT)}
    process = subprocess.Popen(command, stderr=subprocess.PIPE, stdout=subprocess.PIPE,
                               text=True, env=env)
    lines: queue.Queue[str] = queue.Queue()
    assert process.stderr is not None
    threading.Thread(target=_lines, args=(process.stderr, lines), daemon=True).start()
    keyframes, log = 0, []
    try:
        while keyframes < 2:  # synchronised on the CLI's own keyframe events
            line = lines.get(timeout=60)
            assert line, "the run ended before it was interrupted:\n" + "".join(log)
            log.append(line)
            keyframes += json.loads(line).get("event") == "keyframe"
        process.send_signal(signal.SIGINT)
        stdout, _ = process.communicate(timeout=60)
    finally:
        process.kill()
    while (line := lines.get(timeout=10)) != "":
        log.append(line)
    assert process.returncode == ExitCode.INTERRUPTED, "".join(log)
    run = json.loads((out / "run.json").read_text())
    assert run["interrupted"] is True and run["frames"] < 400
    made = sum(json.loads(line).get("event") == "keyframe" for line in log)
    assert read_map_info(saved).num_keyframes == run["map"]["keyframes"] == made >= 2
    assert "map        saved" in stdout
    assert len(read_tum(out / "trajectory.txt")) == run["valid_poses"]


# ----------------------------------------------------------------------------- 15: outputs
@pytest.mark.parametrize(
    ("option", "target", "needle"),
    [
        ("--save-map", "missing/m.kvmap", "does not exist"),
        ("--save-map", "a-folder", "is a folder"),
        ("--rerun", "missing/run.rrd", "does not exist"),
        ("--out", "a-file", "is not a folder"),
    ],
)
def test_output_locations_are_checked_before_anything_runs(
    option: str, target: str, needle: str, tmp_path: Path, simulated_frames: Path,
    simulated_backend: list[str],
) -> None:
    (tmp_path / "a-folder").mkdir()
    (tmp_path / "a-file").write_text("mine\n")
    args = {"--out": tmp_path / "out", option: tmp_path / target}
    result = invoke("track", simulated_frames, *TRACK, *[a for kv in args.items() for a in kv])
    assert result.exit_code == ExitCode.OUTPUT, result.output
    error = next(line for line in result.stderr.splitlines() if line.startswith("error:"))
    assert option in error and needle in error
    assert simulated_backend == []  # refused before the weights were even loaded
    assert not (tmp_path / "out" / "run.json").exists()


def test_an_unwritable_folder_is_refused_before_the_first_frame(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, simulated_frames: Path,
    simulated_backend: list[str],
) -> None:
    def read_only(*args: object, dir: str, **kwargs: object) -> tuple[int, str]:  # noqa: A002
        if Path(dir) == tmp_path / "ro":  # root ignores permission bits: simulate the folder
            raise PermissionError(13, "Permission denied")
        return real(*args, dir=dir, **kwargs)

    real = __import__("tempfile").mkstemp
    monkeypatch.setattr("tempfile.mkstemp", read_only)
    (tmp_path / "ro").mkdir()
    for args in (["--save-map", tmp_path / "ro" / "m.kvmap"], ["--out", tmp_path / "ro"]):
        result = invoke("track", simulated_frames, "--out", tmp_path / "out", *TRACK, *args)
        assert result.exit_code == ExitCode.OUTPUT, result.output
        assert "Permission denied" in result.stderr and simulated_backend == []
    demo = invoke("demo", "--out", tmp_path / "ro", *SMALL_DEMO)
    assert demo.exit_code == ExitCode.OUTPUT and not (tmp_path / "ro" / "run.json").exists()


def test_the_readme_documents_the_exit_codes_the_code_returns() -> None:
    readme = (PROJECT_ROOT / "README.md").read_text()
    paragraph = readme.split("**Exit codes**:", 1)[1].split("\n\n", 1)[0]
    documented = {int(code): text for code, text in re.findall(r"(\d+) ([^·]+)", paragraph)}
    assert set(documented) == set(EXIT_CODES)
    # the issue: a read-only --save-map folder gave 6 while the README said 10
    assert "--save-map" in documented[ExitCode.OUTPUT] and "written" in documented[ExitCode.OUTPUT]
    assert "--save-map" in EXIT_CODES[ExitCode.OUTPUT] and "map" in EXIT_CODES[ExitCode.INTERRUPTED]

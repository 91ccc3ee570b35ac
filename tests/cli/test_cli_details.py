"""Smaller end-of-run and usage details of the CLI: progress while weights are
exported, ``--bbox`` in scene mode, stale outputs of a reused ``--out``, global options after the
command, honest plot units, and FIFOs that must be refused instead of read."""

from __future__ import annotations

import contextlib
import json
import os
import threading
import types
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from kvtracker_sdk.cli.failures import ExitCode
from kvtracker_sdk.errors import BackendError
from kvtracker_sdk.geometry.boxes import box_iou
from tests.cli.invoke import invoke
from tests.helpers import dev_dependency

TRACK = ("--resolution", "224", "--keyframe-interval", "5")
DEMO = ("demo", "--frames", "12", "--size", "60x80", "--resolution", "224")


def _loaded_stand_in(weights: Any) -> types.SimpleNamespace:
    """What ``load_model`` returns, without building the model (the export is cut short)."""
    return types.SimpleNamespace(family="pi3", fingerprint="f" * 16, model=None, name="pi3",
                                 path=Path(weights))


def test_exporting_weights_for_onnx_is_announced_before_it_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, golden_weights: Path, simulated_frames: Path
) -> None:
    dev_dependency("onnxruntime")
    monkeypatch.setenv("KVTRACKER_CACHE_DIR", str(tmp_path / "cache"))  # no cached export
    monkeypatch.setattr("kvtracker_sdk.export_onnx.reuse.load_model", _loaded_stand_in)

    def export_model(*_: Any, **__: Any) -> None:  # the minutes-long export, cut short
        raise BackendError("export stopped by the test")

    monkeypatch.setattr("kvtracker_sdk.export_onnx.reuse.export_model", export_model)
    result = invoke("track", simulated_frames, "--backend", "onnx", "--weights", golden_weights,
                    "--out", tmp_path / "out")
    assert result.exit_code == ExitCode.BACKEND, result.output
    lines = result.stderr.splitlines()
    exporting = next(i for i, line in enumerate(lines) if line.startswith("exporting"))
    assert str(golden_weights) in lines[exporting] and "ONNX" in lines[exporting]
    assert exporting < next(i for i, line in enumerate(lines) if line.startswith("error:"))
    assert not (tmp_path / "out").exists()  # an early failure leaves no empty --out


def test_a_cached_export_is_reused_without_the_export_notice(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, golden_weights: Path, simulated_frames: Path
) -> None:
    dev_dependency("onnxruntime")
    from kvtracker_sdk.export_onnx import reuse

    monkeypatch.setattr(reuse, "load_model", _loaded_stand_in)
    cached = types.SimpleNamespace(weights_fingerprint="f" * 16, sha256={})
    monkeypatch.setattr(reuse, "read_manifest", lambda folder: cached)  # a valid cached export
    monkeypatch.setattr(reuse, "verify_files", lambda folder, sha256: None)
    monkeypatch.setattr(reuse, "export_model", lambda *_, **__: pytest.fail("exported again"))

    def served(*_: Any, **__: Any) -> None:  # the runtime over the cached export, cut short
        raise BackendError("serving stopped by the test")

    monkeypatch.setattr(reuse, "OnnxBackend", served)
    result = invoke("track", simulated_frames, "--backend", "onnx", "--weights", golden_weights,
                    "--out", tmp_path / "out")
    assert result.exit_code == ExitCode.BACKEND, result.output
    assert "serving stopped by the test" in result.stderr
    assert not any(line.startswith("exporting") for line in result.stderr.splitlines())


def test_a_box_in_scene_mode_is_refused(tmp_path: Path, simulated_frames: Path,
                                        simulated_backend: list[str]) -> None:
    result = invoke("track", simulated_frames, "--out", tmp_path, *TRACK, "--bbox", "1,1,50,50")
    assert result.exit_code == ExitCode.CONFIG, result.output
    assert "--bbox is for object mode" in result.stderr and simulated_backend == []


@pytest.mark.usefixtures("simulated_backend")
def test_a_reused_out_keeps_no_output_of_the_previous_run(tmp_path: Path,
                                                           simulated_frames: Path) -> None:
    out = tmp_path / "out"
    first = invoke(*DEMO, "--out", out)  # the demo has a ground truth: evaluation.json
    assert first.exit_code == 0 and (out / "evaluation.json").is_file(), first.output
    (out / "mine.txt").write_text("the user's own file\n")
    second = invoke("track", simulated_frames, "--out", out, *TRACK)  # no ground truth
    assert second.exit_code == 0, second.output
    run = json.loads((out / "run.json").read_text())
    assert run["command"] == "track" and run["evaluation"] is None
    names = {p.name for p in out.iterdir()}
    assert "evaluation.json" not in names and "groundtruth.txt" not in names
    assert {"mine.txt", "trajectory.png", "run.json"} <= names  # others' files stay


def test_global_options_work_after_the_command_and_log_json_alone_logs(tmp_path: Path) -> None:
    alone = invoke(*DEMO, "--out", tmp_path / "a", "--log-json")
    assert alone.exit_code == 0, alone.output
    events = [json.loads(line)["event"] for line in alone.stderr.splitlines()]  # all JSON
    assert "state_change" in events and events[-1] == "run finished"
    quiet = invoke(*DEMO, "--out", tmp_path / "b", "-q")
    assert quiet.exit_code == 0 and quiet.stdout == "" and quiet.stderr == "", quiet.output
    verbose = invoke(*DEMO, "--out", tmp_path / "c", "-vv")
    assert "reason=BOOTSTRAP" in verbose.stderr and "[debug" in verbose.stderr  # per frame


@pytest.mark.usefixtures("simulated_backend")
def test_plots_of_an_unscaled_trajectory_do_not_claim_metres(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, simulated_frames: Path
) -> None:
    from matplotlib.figure import Figure

    labels: list[str] = []
    save = Figure.savefig

    def recording_savefig(self: Figure, *args: Any, **kwargs: Any) -> None:
        labels.extend(label for ax in self.axes for label in (ax.get_xlabel(), ax.get_ylabel()))
        save(self, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", recording_savefig)
    result = invoke("track", simulated_frames, "--out", tmp_path / "t", *TRACK)  # no ground truth
    assert result.exit_code == 0, result.output
    assert labels and all("[arbitrary scale]" in label for label in labels)
    labels.clear()
    demo = invoke(*DEMO, "--out", tmp_path / "d")  # Sim(3)-aligned onto metric ground truth
    assert demo.exit_code == 0 and labels and all("[m]" in label for label in labels[:6])


@contextlib.contextmanager
def fifo(path: Path) -> Iterator[Path]:
    """A FIFO nobody writes to; after 20 s (the code under test hangs: a failure) a writer
    feeds it one line so that the test ends instead of hanging."""
    os.mkfifo(path)
    done = threading.Event()

    def unblock() -> None:
        if not done.wait(20):
            with contextlib.suppress(OSError):  # ENXIO: nobody is reading it after all
                fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
                os.write(fd, b"hung\n")
                os.close(fd)

    thread = threading.Thread(target=unblock, daemon=True)
    thread.start()
    try:
        yield path
    finally:
        done.set()
        thread.join()


def test_fifos_are_refused_instead_of_read(tmp_path: Path, simulated_frames: Path,
                                           simulated_backend: list[str]) -> None:
    masks = tmp_path / "masks"
    masks.mkdir()
    (tmp_path / "gt.txt").write_text("0.0 0 0 0 0 0 0 1\n")
    with fifo(tmp_path / "config.json") as config:
        result = invoke("track", simulated_frames, "--out", tmp_path / "o", "--config", config)
    assert result.exit_code == ExitCode.CONFIG and "FIFO" in result.stderr, result.output
    with fifo(tmp_path / "est.txt") as est:
        result = invoke("eval", est, tmp_path / "gt.txt")
    assert result.exit_code == ExitCode.INPUT and "FIFO" in result.stderr, result.output
    with fifo(masks / "0.png"):
        result = invoke("track", simulated_frames, "--out", tmp_path / "o", "--mode", "object",
                        "--masks", masks)
    assert result.exit_code == ExitCode.INPUT, result.output
    assert "0.png is not a regular file" in result.stderr
    assert simulated_backend == []


@pytest.mark.usefixtures("simulated_backend")
def test_track_an_object_from_one_box(tmp_path: Path, simulated_frames: Path) -> None:
    # the orbit (15 deg per frame, 1 cm of noise) keeps the sphere in the middle of the 252x196
    # frames, about 80 px wide
    result = invoke("track", simulated_frames, "--out", tmp_path, "--resolution", "224",
                    "--mode", "object", "--bbox", "86,58,166,138", "--bbox-once")
    assert result.exit_code == 0, result.output
    frames = json.loads((tmp_path / "object.json").read_text())["frames"]
    assert [f["source"] for f in frames] == ["given"] + ["predicted"] * (len(frames) - 1)
    assert all(box_iou(tuple(f["box"]), (86, 58, 166, 138)) > 0.8 for f in frames)
    refused = invoke("track", simulated_frames, "--out", tmp_path / "b", "--mode", "object",
                     "--bbox-once")
    assert refused.exit_code == ExitCode.CONFIG and "--bbox-once needs --bbox" in refused.stderr

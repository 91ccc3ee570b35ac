"""Every entry point tracks the same way: for one config and one backend, ``kvtracker track``,
``eval-many`` on the serial, local and Ray engines and the documented Python loop write the same
trajectory file, byte for byte — on the shared TUM sequence (its published, distorted camera)
and on two simulated recordings (one with a camera file), for the PyTorch and ONNX backends.
``eval-many`` also runs an OpenVINO config, and each row of its table equals the single run.

Cost: 3 short sequences x 3 backends on the serial engine, x 2 backends (torch, ONNX) on the
local pool and on Ray (one worker each; the session's Ray and ONNX export), and one single run
of the CLI and of the loop per sequence and backend.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from kvtracker_sdk.backends.base import Backend
from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.eval.report import evaluate_trajectories
from kvtracker_sdk.io.files.trajectory import read_trajectory, write_tum
from kvtracker_sdk.io.sources.sources import open_source
from kvtracker_sdk.runs import (
    FrameSelection,
    RunRecord,
    open_backend,
    open_input,
    open_tracker,
    track,
)
from kvtracker_sdk.scale import EvalManyResult, load_manifest, run_many
from tests.cli.invoke import invoke
from tests.helpers import dev_dependency, shared_path
from tests.scale.recordings import write_camera, write_image_folder, write_tum_layout

FRAMES = 4  # per sequence: two mapping passes at a keyframe every 2 frames (a rebuild joins)
CONFIG = {"resolution": 224, "keyframing": {"interval_frames": 2}}
ENGINES = ("serial", "local", "ray")


class Plan:
    """The sequences, the backends and what every entry point wrote."""

    def __init__(self, folder: Path, onnx_folder: Path) -> None:
        self.folder = folder
        tum = shared_path("data", "tum_fr2_desk")
        sim_a = write_tum_layout(folder / "sim_a", FRAMES, seed=3)
        sim_b, sim_b_truth = write_image_folder(folder / "sim_b", FRAMES, seed=4)
        camera = write_camera(folder / "sim_a_camera.json")
        # name -> (input, ground truth or None, camera file or None)
        self.sequences: dict[str, tuple[Path, Path | None, Path | None]] = {
            "tum": (tum, None, None),  # TUM's published fr2 camera: distortion
            "sim_a": (sim_a, None, camera),
            "sim_b": (sim_b, sim_b_truth, None),
        }
        weights = shared_path("golden", "pi3", "weights.safetensors")
        # config name -> (kind, weights)
        self.backends = {"torch": ("torch", weights), "onnx": ("onnx", onnx_folder),
                         "openvino": ("openvino", onnx_folder)}
        # (sequence, config) -> what a single run gave, made once for both tests
        self.cli_runs: dict[tuple[str, str], Path] = {}
        self.loop_runs: dict[tuple[str, str], tuple[Path, RunRecord]] = {}
        self.opened: dict[str, Backend] = {}  # the loop's backends, opened once per runtime

    def backend(self, config: str) -> Backend:
        if config not in self.opened:
            kind, weights = self.backends[config]
            self.opened[config] = open_backend(kind, weights, threads=1)
        return self.opened[config]

    def manifest(self, configs: tuple[str, ...]) -> Path:
        sequences = []
        for name, (source, truth, camera) in self.sequences.items():
            entry: dict[str, Any] = {"name": name, "source": str(source), "frames": FRAMES}
            if truth is not None:
                entry["ground_truth"] = str(truth)
            if camera is not None:
                entry["camera"] = str(camera)
            sequences.append(entry)
        backends = {name: {**CONFIG, "backend": {"kind": kind, "weights": str(weights)}}
                    for name, (kind, weights) in self.backends.items() if name in configs}
        path = self.folder / f"manifest_{'_'.join(configs)}.json"
        path.write_text(json.dumps({"configs": backends, "sequences": sequences}))
        return path


@pytest.fixture(scope="module")
def plan(tmp_path_factory: pytest.TempPathFactory,
         onnx_exports: Callable[[str], Any]) -> Iterator[Plan]:
    dev_dependency("openvino")
    made = Plan(tmp_path_factory.mktemp("one_path"), onnx_exports("pi3").folder)
    yield made
    for backend in made.opened.values():
        backend.close()


@pytest.fixture(scope="module")
def engines(plan: Plan, ray_session: Any) -> dict[str, EvalManyResult]:
    """Serial: every runtime; the local pool and Ray: torch and ONNX (an OpenVINO compile in each
    worker would add cost and no evidence: the engines share one task function)."""
    every = load_manifest(plan.manifest(("torch", "onnx", "openvino")))
    two = load_manifest(plan.manifest(("torch", "onnx")))
    return {engine: run_many(every if engine == "serial" else two, plan.folder / engine,
                             engine=engine, workers=1) for engine in ENGINES}


def _cli_run(plan: Plan, sequence: str, config: str) -> Path:
    if (sequence, config) in plan.cli_runs:
        return plan.cli_runs[sequence, config]
    source, truth, camera = plan.sequences[sequence]
    kind, weights = plan.backends[config]
    out = plan.folder / "cli" / sequence / config
    config_file = plan.folder / "config.json"
    config_file.write_text(json.dumps(CONFIG))
    extra = ["--camera", camera] if camera else []
    result = invoke("-q", "track", source, "--out", out, "--backend", kind, "--weights", weights,
                    "--threads", 1, "--config", config_file, "--max-frames", FRAMES, *extra)
    assert result.exit_code == 0, result.output
    plan.cli_runs[sequence, config] = out / "trajectory.txt"
    return out / "trajectory.txt"


def _python_loop(plan: Plan, sequence: str, config: str) -> tuple[Path, RunRecord]:
    """The loop of docs/backends.md, as an app writes it."""
    if (sequence, config) in plan.loop_runs:
        return plan.loop_runs[sequence, config]
    source, truth, camera = plan.sequences[sequence]
    backend = plan.backend(config)  # open_backend(kind, weights, threads=1), once per runtime
    run_input = open_input(source, camera=camera, ground_truth=truth)
    with open_tracker(TrackerConfig.from_dict(CONFIG), backend, run_input) as tracker:
        record = track(tracker, run_input, selection=FrameSelection(max_frames=FRAMES))
    path = plan.folder / "loop" / sequence / f"{config}.txt"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_tum(path, record.trajectory())
    plan.loop_runs[sequence, config] = path, record
    return path, record


@pytest.mark.parametrize("config", ["torch", "onnx"])
@pytest.mark.parametrize("sequence", ["tum", "sim_a", "sim_b"])
def test_every_entry_point_writes_the_same_trajectory(
    plan: Plan, engines: dict[str, EvalManyResult], sequence: str, config: str
) -> None:
    reference = _cli_run(plan, sequence, config).read_bytes()
    assert reference.count(b"\n") >= FRAMES - 1  # the header and the valid poses
    for engine in ENGINES:
        written = plan.folder / engine / sequence / config / "trajectory.txt"
        assert written.read_bytes() == reference, f"eval-many --engine {engine}"
    assert _python_loop(plan, sequence, config)[0].read_bytes() == reference, "the Python loop"


@pytest.mark.parametrize("sequence", ["tum", "sim_a", "sim_b"])
def test_the_table_has_a_row_per_runtime_equal_to_single_runs(
    plan: Plan, engines: dict[str, EvalManyResult], sequence: str
) -> None:
    rows = {r.config: r for r in engines["serial"].results if r.sequence == sequence}
    assert {name: row.backend for name, row in rows.items()} == {
        "torch": "torch/float32", "onnx": "onnx/float32", "openvino": "openvino/float32"}
    source, truth_file, _camera = plan.sequences[sequence]
    truth = read_trajectory(truth_file) if truth_file else open_source(source).ground_truth()
    assert truth is not None
    for config, row in rows.items():
        _path, record = _python_loop(plan, sequence, config)
        # scored from the single run's poses in memory: a TUM file keeps rotations as
        # quaternions, so RPE from a re-read file differs in the 7th digit
        single = evaluate_trajectories(record.trajectory(), truth)
        assert row.error is None and row.frames == record.num_frames == FRAMES
        assert row.valid_poses == len(record.trajectory()) and row.keyframes == record.num_keyframes
        assert (row.ate_rmse_m, row.rpe_translation_rmse_m, row.rpe_rotation_rmse_deg) == (
            single.ate.translation.rmse, single.rpe.translation.rmse, single.rpe.rotation_deg.rmse)
        if (sequence, config) in plan.cli_runs:  # torch and ONNX: the CLI ran it above
            run = json.loads((plan.cli_runs[sequence, config].parent / "run.json").read_text())
            assert run["backend"]["runtime"] == config and run["valid_poses"] == row.valid_poses
            if run["evaluation"] and "ate" in run["evaluation"]:  # the CLI scored it too
                assert run["evaluation"]["ate"]["translation"]["rmse"] == row.ate_rmse_m
    serial = [m for m in engines["serial"].metrics() if m["config"] != "openvino"]
    for engine in ("local", "ray"):
        assert engines[engine].metrics() == serial

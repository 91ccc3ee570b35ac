"""One evaluation task: a sequence under one configuration, tracked and scored.

The same function runs in the caller's process (``--engine serial``), in a process-pool worker
(``local``) and in a Ray actor (``ray``): engines differ only in where it runs, so their numbers
are identical. What could make them differ is pinned here: torch's thread count (reductions split
across threads add in another order) is set per task, and mapping runs as the configuration says
(keep ``threading.async_mapping`` off, the default, for bit-identical poses).

A task tracks through the library's one path (``runs``: ``open_input`` with the sequence's
camera, ``open_tracker``, ``track``), so its trajectory is byte for byte the one ``kvtracker
track`` writes for the same config, backend and thread count.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.errors import ConfigError, EvaluationError, KVTrackerError
from kvtracker_sdk.io.files.atomic import atomic_write
from kvtracker_sdk.io.files.trajectory import Trajectory, write_tum
from kvtracker_sdk.runs.frames import FrameSelection
from kvtracker_sdk.runs.run_loop import InputFrame
from kvtracker_sdk.scale.manifest import SequenceSpec, SimulatedSpec, safe_name

if TYPE_CHECKING:
    from kvtracker_sdk.backends.base import Backend

__all__ = [
    "BackendProvider",
    "SequenceResult",
    "output_folder",
    "run_sequence",
    "simulated_sequence",
    "torch_threads",
]

BackendProvider = Callable[[], "Backend"]  # the config's backend, opened at most once per worker


@dataclass(frozen=True)
class SequenceResult:
    """The numbers of one (sequence, config) run; ``metrics()`` excludes where and how long."""

    sequence: str
    config: str
    backend: str  # the runtime that ran it: "torch/float32", "onnx/float32", ..., "simulated"
    simulated: bool
    frames: int
    valid_poses: int
    keyframes: int
    ate_rmse_m: float | None  # Sim(3)-aligned translation RMSE (the paper's ATE)
    rpe_translation_rmse_m: float | None
    rpe_rotation_rmse_deg: float | None
    error: str | None  # why there are no metrics (a typed SDK error), None when scored
    wall_seconds: float
    worker: str
    worker_model_loads: int = 0  # how often the worker had read weights by then (at most 1)

    def metrics(self) -> dict[str, Any]:
        row = asdict(self)
        del row["wall_seconds"], row["worker"], row["worker_model_loads"]
        return row

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@contextmanager
def torch_threads(count: int) -> Iterator[None]:
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def simulated_sequence(spec: SimulatedSpec) -> tuple[Backend, Iterator[InputFrame], Trajectory]:
    from kvtracker_sdk.backends.simulated import SimulatedBackend
    from kvtracker_sdk.backends.simulated_scene import GroundTruth, orbit

    if spec.ground_truth is not None:
        truth = GroundTruth.from_tum(spec.ground_truth, rate_hz=30.0)
        if spec.frames is not None:
            truth = GroundTruth(truth.timestamps[: spec.frames].copy(), truth.poses[: spec.frames].copy())
    else:
        assert spec.orbit_frames is not None  # the manifest validated it
        truth = orbit(spec.orbit_frames, turns=spec.orbit_turns)
    backend = SimulatedBackend(
        truth, translation_noise_m=spec.noise_cm / 100.0, rotation_noise_deg=spec.noise_deg,
        loss_segments=[spec.loss] if spec.loss else [], seed=spec.seed,
    )
    # flat frames: the simulated backend reads its frame index from the pixels, texture is
    # only for people looking at a demo, and rendering it would dominate the run's time
    frames = (InputFrame(f.image, f.timestamp) for f in backend.frames(spec.size, textured=False))
    return backend, frames, Trajectory(truth.timestamps, truth.poses)


def output_folder(out_dir: Path, sequence: str, config: str) -> Path:
    """``out_dir/<sequence>/<config>``, the names validated (``safe_name``), never joined raw: a
    name ``..``, an absolute path or one with a separator would put files outside ``out_dir``."""
    folder = Path(out_dir) / safe_name(sequence, "sequence name") / safe_name(config, "config name")
    root = Path(out_dir).resolve()
    if not folder.resolve().is_relative_to(root):  # a symlink inside out_dir leading out
        raise ConfigError(f"output folder {folder} leads outside --out {root}")
    return folder


def run_sequence(
    spec: SequenceSpec,
    config_name: str,
    config: TrackerConfig,
    provider: BackendProvider,
    out_dir: Path,
    *,
    threads: int = 1,
    worker: str = "main",
    model_loads: Callable[[], int] = lambda: 0,
    backend_label: str = "torch/float32",
) -> SequenceResult:
    """Track ``spec`` under ``config``, write ``out_dir/<sequence>/<config>/`` (trajectory.txt,
    result.json) and return the numbers. A typed SDK error in scoring becomes the result's
    ``error``; anything else propagates (a bug, not a result)."""
    from kvtracker_sdk.eval.report import evaluate_trajectories
    from kvtracker_sdk.runs.inputs import open_input
    from kvtracker_sdk.runs.session import open_tracker, track

    folder = output_folder(out_dir, spec.name, config_name)  # before any work: a bad name fails fast
    start = time.perf_counter()
    with torch_threads(threads):
        if spec.simulated is not None:
            backend, frames, truth = simulated_sequence(spec.simulated)
            with open_tracker(config, backend) as tracker:
                record = track(tracker, frames)
        else:
            assert spec.source is not None  # the manifest validated it
            run_input = open_input(spec.source, camera=spec.camera, ground_truth=spec.ground_truth)
            if run_input.ground_truth is None:
                raise EvaluationError(f"sequence {spec.name}: no ground truth (give ground_truth)")
            truth = run_input.ground_truth
            with open_tracker(config, provider(), run_input) as tracker:
                record = track(tracker, run_input, selection=FrameSelection(max_frames=spec.frames))
    if record.failure is not None:  # not a result: a bad frame, or a bug
        raise record.failure
    if record.interrupted:  # Ctrl-C: a partial run is not a row of the table
        raise KeyboardInterrupt
    results, keyframes = record.results, record.num_keyframes
    estimate = record.trajectory()
    valid = estimate.poses
    ate = rpe_t = rpe_r = None
    error = None
    try:
        report = evaluate_trajectories(estimate, truth)
        ate = float(report.ate.translation.rmse)
        rpe_t, rpe_r = float(report.rpe.translation.rmse), float(report.rpe.rotation_deg.rmse)
    except KVTrackerError as exc:
        error = f"{type(exc).__name__}: {exc}"
    result = SequenceResult(
        spec.name, config_name, backend_label if spec.simulated is None else "simulated",
        spec.simulated is not None, len(results), len(valid), keyframes,
        ate, rpe_t, rpe_r, error, time.perf_counter() - start, worker, model_loads(),
    )
    folder.mkdir(parents=True, exist_ok=True)
    if len(valid):
        write_tum(folder / "trajectory.txt", estimate)
    with atomic_write(folder / "result.json") as handle:
        json.dump(result.to_dict(), handle, indent=2)
    return result

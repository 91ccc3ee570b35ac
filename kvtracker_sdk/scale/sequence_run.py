"""One evaluation task: a sequence under one configuration, tracked and scored.

The same function runs in the caller's process (``--engine serial``), in a process-pool worker
(``local``) and in a Ray actor (``ray``): engines differ only in where it runs, so their numbers
are identical. What could make them differ is pinned here: torch's thread count (reductions split
across threads add in another order) is set per task, and mapping runs as the configuration says
(keep ``threading.async_mapping`` off, the default, for bit-identical poses).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.errors import ConfigError, EvaluationError, KVTrackerError
from kvtracker_sdk.io.atomic import atomic_write
from kvtracker_sdk.io.trajectory import Trajectory, read_trajectory, write_tum
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

BackendProvider = Callable[[], "Backend"]  # the worker's model, loaded at most once


@dataclass(frozen=True)
class SequenceResult:
    """The numbers of one (sequence, config) run; ``metrics()`` excludes where and how long."""

    sequence: str
    config: str
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


def simulated_sequence(spec: SimulatedSpec) -> tuple[Backend, Iterator[tuple[np.ndarray, float]], Trajectory]:
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
    frames = ((f.image, f.timestamp) for f in backend.frames(spec.size, textured=False))
    return backend, frames, Trajectory(truth.timestamps, truth.poses)


def _real(
    spec: SequenceSpec, provider: BackendProvider
) -> tuple[Backend, Iterator[tuple[np.ndarray, float]], Trajectory]:
    from kvtracker_sdk.io.sources import open_source

    assert spec.source is not None
    source = open_source(spec.source)
    truth = read_trajectory(spec.ground_truth) if spec.ground_truth else source.ground_truth()
    if truth is None:
        raise EvaluationError(f"sequence {spec.name}: no ground truth (give ground_truth)")
    limit = spec.frames if spec.frames is not None else len(source)
    frames = ((f.image, f.timestamp) for f in source if f.frame_index < limit)
    return provider(), frames, truth


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
) -> SequenceResult:
    """Track ``spec`` under ``config``, write ``out_dir/<sequence>/<config>/`` (trajectory.txt,
    result.json) and return the numbers. A typed SDK error in scoring becomes the result's
    ``error``; anything else propagates (a bug, not a result)."""
    from kvtracker_sdk.eval.report import evaluate_trajectories
    from kvtracker_sdk.tracking.tracker import Tracker

    folder = output_folder(out_dir, spec.name, config_name)  # before any work: a bad name fails fast
    start = time.perf_counter()
    with torch_threads(threads):
        if spec.simulated is not None:
            backend, frames, truth = simulated_sequence(spec.simulated)
        else:
            backend, frames, truth = _real(spec, provider)
        tracker = Tracker(config, backend)  # does not close a backend it was given
        try:
            results = [tracker.push_frame(image, timestamp=stamp) for image, stamp in frames]
            tracker.wait_for_map(timeout=None)
            keyframes = tracker.map_status.num_keyframes
        finally:
            tracker.close()
    valid = [r for r in results if r.pose_valid and r.pose is not None]
    estimate = Trajectory(
        np.array([r.timestamp for r in valid], dtype=np.float64),
        np.array([r.pose.T_world_cam for r in valid if r.pose is not None]).reshape(-1, 4, 4),
    )
    ate = rpe_t = rpe_r = None
    error = None
    try:
        report = evaluate_trajectories(estimate, truth)
        ate = float(report.ate.translation.rmse)
        rpe_t, rpe_r = float(report.rpe.translation.rmse), float(report.rpe.rotation_deg.rmse)
    except KVTrackerError as exc:
        error = f"{type(exc).__name__}: {exc}"
    result = SequenceResult(
        spec.name, config_name, spec.simulated is not None, len(results), len(valid), keyframes,
        ate, rpe_t, rpe_r, error, time.perf_counter() - start, worker, model_loads(),
    )
    folder.mkdir(parents=True, exist_ok=True)
    if len(valid):
        write_tum(folder / "trajectory.txt", estimate)
    with atomic_write(folder / "result.json") as handle:
        json.dump(result.to_dict(), handle, indent=2)
    return result

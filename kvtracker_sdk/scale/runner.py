"""``run_many``: every (sequence, config) task of a manifest on one of three engines.

* ``serial`` — one by one in this process (the reference the others must equal);
* ``local`` — a process pool (spawned workers, each loading the model once in its initializer);
* ``ray`` — a pool of Ray actors (each loading the model once when created), on a Ray cluster
  already connected to, or on a local one started bound to 127.0.0.1 (``ray_runtime``).

All three call ``sequence_run.run_sequence`` with the same arguments, so they give the same
numbers. Each config runs on its own backend (``EvalManifest.backend_spec``), which a worker opens
once, on its first task of that config. Tasks cross process boundaries as JSON strings of the manifest's own models and come back
as plain dicts: nothing of ours is unpickled from a file, and weights travel only as a path.
"""

from __future__ import annotations

import enum
import json
import os
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.runs.backends import BackendSpec
from kvtracker_sdk.scale.manifest import EvalManifest, ModelSpec, SequenceSpec
from kvtracker_sdk.scale.model_cache import ModelCache
from kvtracker_sdk.scale.results import EvalManyResult
from kvtracker_sdk.scale.sequence_run import SequenceResult, run_sequence

__all__ = ["Engine", "EvalManyResult", "run_many"]

_log = get_logger(__name__)

Progress = Callable[[int, int, SequenceResult], Any]


class Engine(str, enum.Enum):
    SERIAL = "serial"
    LOCAL = "local"
    RAY = "ray"


# (sequence JSON, config name, TrackerConfig JSON, backend spec JSON or "") — what one task
# ships to a worker
_Task = tuple[str, str, str, str]


def _tasks(manifest: EvalManifest) -> list[_Task]:
    tasks: list[_Task] = []
    for spec, name in manifest.tasks():
        backend = manifest.backend_spec(name)
        fields = {k: v for k, v in manifest.configs[name].items() if k != "backend"}
        tasks.append((spec.model_dump_json(), name, json.dumps(fields),
                      "" if backend is None else backend.model_dump_json()))
    return tasks


class TaskWorker:
    """Runs tasks with one model loaded at most once: the body of a pool worker and a Ray actor."""

    def __init__(self, model_json: str | None, out_dir: str, threads: int) -> None:
        model = ModelSpec.model_validate_json(model_json) if model_json else None
        # the task's thread count for every runtime: results depend on how reductions split
        self._models = ModelCache(model, threads=threads)
        self._out_dir = Path(out_dir)
        self._threads = threads
        self._name = f"pid{os.getpid()}"

    def run(self, task: _Task) -> dict[str, Any]:
        from kvtracker_sdk.config import TrackerConfig

        spec_json, config_name, config_json, backend_json = task
        spec = SequenceSpec.model_validate_json(spec_json)
        config = TrackerConfig.from_dict(json.loads(config_json))
        backend = BackendSpec.model_validate_json(backend_json) if backend_json else None
        result = run_sequence(spec, config_name, config, lambda: self._models.get(backend),
                              self._out_dir, threads=self._threads, worker=self._name,
                              model_loads=lambda: self._models.loads,
                              backend_label=backend.label() if backend else "none")
        return result.to_dict()

    @property
    def model_loads(self) -> int:
        return self._models.loads


_POOL_WORKER: TaskWorker | None = None  # one per pool process, made by its initializer


def _init_pool_worker(model_json: str | None, out_dir: str, threads: int) -> None:
    global _POOL_WORKER
    _POOL_WORKER = TaskWorker(model_json, out_dir, threads)


def _run_in_pool(task: _Task) -> dict[str, Any]:
    assert _POOL_WORKER is not None, "pool worker not initialised"
    return _POOL_WORKER.run(task)


def _serial(manifest: EvalManifest, out_dir: Path, tasks: list[_Task]) -> Iterator[dict[str, Any]]:
    model_json = manifest.model.model_dump_json() if manifest.model else None
    worker = TaskWorker(model_json, str(out_dir), manifest.threads_per_task)
    for task in tasks:
        yield worker.run(task)


def _local(
    manifest: EvalManifest, out_dir: Path, tasks: list[_Task], workers: int
) -> Iterator[dict[str, Any]]:
    model_json = manifest.model.model_dump_json() if manifest.model else None
    # spawn, not fork: a forked child would inherit torch's thread pools and locks mid-state
    with ProcessPoolExecutor(
        max_workers=workers, mp_context=get_context("spawn"), initializer=_init_pool_worker,
        initargs=(model_json, str(out_dir), manifest.threads_per_task),
    ) as pool:
        futures = [pool.submit(_run_in_pool, task) for task in tasks]
        for future in as_completed(futures):
            yield future.result()


def _ray(
    manifest: EvalManifest, out_dir: Path, tasks: list[_Task], workers: int
) -> Iterator[dict[str, Any]]:
    from kvtracker_sdk.scale.ray_runtime import actor_class, ensure_ray

    ray = ensure_ray(num_cpus=workers)
    from ray.util import ActorPool

    model_json = manifest.model.model_dump_json() if manifest.model else None
    # one CPU per actor, or a share of a smaller cluster: an actor asking for more CPUs than the
    # cluster has would never start, and the tasks queued on it would wait forever
    share = min(1.0, float(ray.cluster_resources().get("CPU", 1.0)) / workers)
    remote_worker = actor_class(TaskWorker, num_cpus=share)
    actors = [
        remote_worker.remote(model_json, str(out_dir), manifest.threads_per_task)
        for _ in range(workers)
    ]
    try:
        pool = ActorPool(actors)
        yield from pool.map_unordered(lambda actor, task: actor.run.remote(task), tasks)
    finally:
        for actor in actors:
            ray.kill(actor)


def run_many(
    manifest: EvalManifest,
    out_dir: str | Path,
    *,
    engine: Engine | str = Engine.LOCAL,
    workers: int = 2,
    progress: Progress | None = None,
) -> EvalManyResult:
    """Run every task of ``manifest``; write per-task folders and the summary table in
    ``out_dir``; return the results in manifest order."""
    engine = Engine(engine)
    if workers < 1:
        raise ConfigError(f"workers must be >= 1, got {workers}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tasks = _tasks(manifest)
    if engine is Engine.SERIAL:
        stream = _serial(manifest, out, tasks)
    elif engine is Engine.LOCAL:
        stream = _local(manifest, out, tasks, workers)
    else:
        stream = _ray(manifest, out, tasks, workers)
    done: list[SequenceResult] = []
    for row in stream:
        result = SequenceResult(**row)
        done.append(result)
        _log.info("sequence done", sequence=result.sequence, config=result.config,
                  ate_rmse_m=result.ate_rmse_m, worker=result.worker)
        if progress is not None:
            progress(len(done), len(tasks), result)
    order = {(spec.name, name): i for i, (spec, name) in enumerate(manifest.tasks())}
    done.sort(key=lambda r: order[(r.sequence, r.config)])
    table = EvalManyResult(tuple(done), engine=engine.value, workers=workers)
    table.write(out)
    return table

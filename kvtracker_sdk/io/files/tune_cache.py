"""The tuner's choice (``backends/autotune.py``) kept per machine and model, in a small JSON file.

A choice holds only for the machine, software and problem it was measured on, so the file's
key is: the CPU model, the usable core count and the CPU vector ISA torch detected; the
versions of the SDK, torch, ONNX Runtime and OpenVINO; the weights (a model name or hub id as
given, a file or folder by its absolute path, size and modification time: cheap to check before
anything loads), the tracker's resolution setting and the keyframe count. One file per key, named by the key's digest, in
``$KVTRACKER_CACHE_DIR/tune``, else ``$XDG_CACHE_HOME/kvtracker_sdk/tune``, else
``~/.cache/kvtracker_sdk/tune`` (beside the ONNX exports' cache, ``export_onnx/reuse.py``).

Written atomically (``io/files/atomic.py``: never half a file, concurrent writers of one key leave one
whole file). Read back validated: a regular file of at most 1 MB, JSON, this schema version,
the full key equal to the one asked for (not only the digest), a known runtime and dtype and a
thread count within the usable cores; anything else is ignored (logged) and tuned again.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any

import torch

from kvtracker_sdk._version import __version__
from kvtracker_sdk.backends.autotune import Candidate, TuneProblem, TuneResult
from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.io.files.atomic import atomic_write
from kvtracker_sdk.io.files.regular_file import read_regular_text
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.threads import usable_cores

__all__ = [
    "SCHEMA",
    "cached_choice",
    "choice_key",
    "remember_choice",
    "tune_cache_dir",
    "weights_identity",
]

_log = get_logger(__name__)
SCHEMA = 1
_MAX_BYTES = 1 << 20


def tune_cache_dir() -> Path:
    """Where choices are kept (see the module docstring)."""
    if root := os.environ.get("KVTRACKER_CACHE_DIR"):
        return Path(root) / "tune"
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "kvtracker_sdk" / "tune"


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            for line in cpuinfo:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(package: str) -> str | None:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


def weights_identity(weights: str | os.PathLike[str]) -> str:
    """``weights`` as the key names them: a path by its absolute path, size and mtime (a file
    replaced in place is another model); anything else (a model name, a hub id) as given."""
    path = Path(weights)
    try:
        status = path.stat()
    except OSError:
        return str(weights)
    return f"{path.resolve()}|{status.st_size}|{status.st_mtime_ns}"


def choice_key(weights: str | os.PathLike[str], problem: TuneProblem) -> dict[str, Any]:
    """The key a choice is kept under: machine, software, weights and problem."""
    return {
        "cpu": _cpu_model(),
        "cores": usable_cores(),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "versions": {"kvtracker_sdk": __version__, "torch": torch.__version__,
                     "onnxruntime": _version("onnxruntime"), "openvino": _version("openvino")},
        "weights": weights_identity(weights),
        "resolution": problem.resolution,
        "size": None if problem.size is None else list(problem.size),
        "keyframes": problem.keyframes,
    }  # fmt: skip


def _path(key: dict[str, Any], folder: Path | None) -> Path:
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:32]
    return (folder or tune_cache_dir()) / f"{digest}.json"


def remember_choice(key: dict[str, Any], result: TuneResult, folder: Path | None = None) -> Path:
    """Write ``result``'s choice under ``key`` (atomically); return the file."""
    path = _path(key, folder)
    path.parent.mkdir(parents=True, exist_ok=True)
    chosen = result.chosen
    record = {
        "schema": SCHEMA,
        "key": key,
        "chosen": {"runtime": chosen.runtime, "dtype": chosen.dtype, "threads": chosen.threads},
        "reason": result.reason,
        "runtimes": sorted({r.candidate.runtime for r in result.results}),
        "model_size": result.extra.get("model_size"),
        "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "interleaved": result.interleaved,
        "load_average": result.load_average,
        "deviation_bound": result.deviation_bound,
        "race": result.extra.get("race"),
        "candidates": [
            {"name": r.candidate.name, "median_s": r.median_s, "best_s": r.best_s,
             "cpu_median_s": r.cpu_median_s, "steps": r.steps, "deviation": r.deviation,
             "eligible": r.eligible, "note": r.note}
            for r in result.results
        ],
    }  # fmt: skip
    with atomic_write(path) as handle:
        json.dump(record, handle, indent=1)
        handle.write("\n")
    return path


def cached_choice(
    key: dict[str, Any], folder: Path | None = None
) -> tuple[Candidate, str] | None:
    """The choice kept under ``key`` and its reason, or None (absent or not valid: logged)."""
    path = _path(key, folder)
    if not path.exists():
        return None
    try:
        if path.stat().st_size > _MAX_BYTES:
            raise ConfigError(f"larger than {_MAX_BYTES} bytes")
        record = json.loads(read_regular_text(path, ConfigError, what="tune choice"))
        if not isinstance(record, dict) or record.get("schema") != SCHEMA:
            raise ConfigError("not a tune choice of this schema")
        if record.get("key") != key:
            raise ConfigError("made for another machine, software or problem")
        chosen = record["chosen"]
        threads = chosen["threads"]
        if threads is not None and (not isinstance(threads, int) or threads > usable_cores()):
            raise ConfigError(f"threads {threads!r} outside this machine's cores")
        candidate = Candidate(str(chosen["runtime"]), str(chosen["dtype"]), threads)
        return candidate, str(record.get("reason", ""))
    except (OSError, ValueError, KeyError, TypeError, ConfigError) as exc:
        _log.warning("tune choice ignored", path=str(path), reason=str(exc)[:200])
        return None

"""What a user can trigger is a ``KVTrackerError``: public constructors and functions fed bad input.

``test_public_api.py`` checks the classes of ``errors.py``; this file checks what the public
callables actually raise. Each case was an untyped error before (pydantic's ValidationError,
SafetensorError, ValueError, OverflowError, RecursionError, AssertionError, torch's RuntimeError);
the expected class is the most specific typed one. The CLI cases check the exit codes they map to.
"""

from __future__ import annotations

import io
import json
import pickle
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from safetensors.torch import save

import kvtracker_sdk as sdk
from kvtracker_sdk import errors
from kvtracker_sdk.backends.onnx_manifest import MANIFEST_NAME, read_manifest
from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.cache.kv_cache import CacheLayout
from kvtracker_sdk.cli.failures import ExitCode
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.io.files.trajectory import read_tum
from kvtracker_sdk.io.map_file.map_file import load_map
from kvtracker_sdk.models.da3.config import DA3Config
from kvtracker_sdk.models.pi3.config import Pi3Config
from kvtracker_sdk.models.registry import load_model
from tests.cli.invoke import invoke
from tests.helpers import shared_path

NUL_PATH = "/tmp/kvtracker\0.kvmap"
DEEP_JSON = '{"a":' * 100_000 + "1" + "}" * 100_000  # beyond the interpreter's recursion limit


def not_safetensors(kind: str) -> bytes:
    """Files a user may name ``.safetensors`` by mistake."""
    if kind == "pickle":
        return pickle.dumps({"register_token": [0.0]})
    if kind == "zip":  # what torch.save writes
        buffer = io.BytesIO()
        with zipfile.ZipFile(buffer, "w") as archive:
            archive.writestr("archive/data.pkl", b"\x80\x04")
        return buffer.getvalue()
    if kind == "truncated":
        return save({"register_token": torch.zeros(8)})[:-5]
    return b""


@pytest.mark.parametrize("kind", ["pickle", "zip", "empty", "truncated"])
def test_a_file_that_is_not_safetensors_is_a_model_error(tmp_path: Path, kind: str) -> None:
    path = tmp_path / "model.safetensors"
    path.write_bytes(not_safetensors(kind))
    for load in (load_model, sdk.TorchBackend.from_pretrained):
        with pytest.raises(errors.ModelError, match="not a readable .safetensors checkpoint"):
            load(path)


def sim_tracker() -> Any:
    return sdk.Tracker(sdk.TrackerConfig(), sdk.SimulatedBackend(orbit(30, turns=0.25)))


CASES: list[tuple[str, type[errors.KVTrackerError], Callable[[], Any]]] = [
    ("load_map NUL path", errors.MapIOError, lambda: load_map(NUL_PATH)),
    ("read_map_info NUL path", errors.MapIOError, lambda: sdk.read_map_info(NUL_PATH)),
    ("read_tum NUL path", errors.TrajectoryError, lambda: read_tum(NUL_PATH)),
    ("load_model NUL path", errors.ModelError, lambda: load_model(NUL_PATH)),
    (
        "Tracker.from_map NUL path",
        errors.MapIOError,
        lambda: sdk.Tracker.from_map(NUL_PATH, sdk.SimulatedBackend(orbit(30, turns=0.25))),
    ),
    (
        "push_frame timestamp 10**400",
        errors.InputError,
        lambda: sim_tracker().push_frame(np.zeros((64, 64, 3), np.uint8), timestamp=10**400),
    ),
    ("Pose of a 3-vector", errors.InputError, lambda: sdk.Pose(np.zeros(3))),
    ("Pose of text", errors.InputError, lambda: sdk.Pose([["a"] * 4] * 4)),  # type: ignore[arg-type]
    ("Sim3 scale 0", errors.InputError, lambda: Sim3(np.eye(3), np.zeros(3), 0.0)),
    ("Sim3 2x2 rotation", errors.InputError, lambda: Sim3(np.eye(2), np.zeros(3))),
    ("Pi3Config unknown field", errors.ConfigError, lambda: Pi3Config(dim=-1)),  # type: ignore[call-arg]
    (
        "Pi3Config bad value",
        errors.ConfigError,
        lambda: Pi3Config(**{**Pi3Config.large().model_dump(), "patch_size": "x"}),
    ),
    ("DA3Config bad value", errors.ConfigError, lambda: DA3Config(patch_size="x")),  # type: ignore[arg-type]
    ("CacheLayout negative heads", errors.CacheError, lambda: CacheLayout((1,), -2, 8)),
    ("TrackerConfig bad value", errors.ConfigError, lambda: sdk.TrackerConfig(resolution=5)),  # type: ignore[arg-type]
]


@pytest.mark.parametrize(("name", "expected", "call"), CASES, ids=[c[0] for c in CASES])
def test_public_callables_raise_typed_errors(
    name: str, expected: type[errors.KVTrackerError], call: Callable[[], Any]
) -> None:
    with pytest.raises(errors.KVTrackerError) as caught:
        call()
    assert isinstance(caught.value, expected), f"{name}: {type(caught.value).__mro__}"


def test_a_deeply_nested_manifest_is_a_model_error(tmp_path: Path) -> None:
    (tmp_path / MANIFEST_NAME).write_text(DEEP_JSON)
    with pytest.raises(errors.ModelError, match="cannot read"):
        read_manifest(tmp_path)


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_without_cuda_is_a_backend_error() -> None:
    weights = shared_path("golden", "pi3", "weights.safetensors")
    with pytest.raises(errors.BackendError, match="CUDA is not available"):
        sdk.TorchBackend.from_pretrained(weights, device="cuda")
    with pytest.raises(errors.ConfigError, match="unknown device"):
        sdk.TorchBackend.from_pretrained(weights, device="no-such-device")


# ------------------------------------------------------------------------------------- CLI
def cli_track(tmp_path: Path, *options: object) -> Any:
    frames = shared_path("data", "tum_fr2_desk")
    return invoke("track", frames, "--out", tmp_path / "out", "--max-frames", 2, *options)


def test_cli_a_pickle_as_weights_exits_4(tmp_path: Path) -> None:
    weights = tmp_path / "model.safetensors"
    weights.write_bytes(not_safetensors("pickle"))
    result = cli_track(tmp_path, "--weights", weights)
    assert result.exit_code == ExitCode.WEIGHTS, result.stderr
    assert "bug" not in result.stderr


def test_cli_a_deeply_nested_config_exits_8(tmp_path: Path) -> None:
    config = tmp_path / "config.json"
    config.write_text(DEEP_JSON)
    weights = shared_path("golden", "pi3", "weights.safetensors")
    result = cli_track(tmp_path, "--weights", weights, "--config", config)
    assert result.exit_code == ExitCode.CONFIG, result.stderr


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cli_cuda_without_cuda_exits_9(tmp_path: Path) -> None:
    weights = shared_path("golden", "pi3", "weights.safetensors")
    result = cli_track(tmp_path, "--weights", weights, "--device", "cuda")
    assert result.exit_code == ExitCode.BACKEND, result.stderr
    assert "CUDA is not available" in result.stderr


def test_deep_json_is_deeper_than_the_recursion_limit() -> None:
    with pytest.raises(RecursionError):
        json.loads(DEEP_JSON)

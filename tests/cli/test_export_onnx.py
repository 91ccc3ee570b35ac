"""``kvtracker export-onnx``: the session's golden exports (made by this command, see
``tests/conftest.py::onnx_exports``), the random-weights path of a config file, and
``kvtracker track --backend onnx`` reading an export.

Exports are the slowest thing the suite does (30-60 s of CPU each): the command's real export
is the session's one per family; the random-weights test checks what the command hands to the
exporter (network, weights fingerprint, check size) without exporting again.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from kvtracker_sdk.cli.export_onnx import parse_size
from kvtracker_sdk.cli.failures import ExitCode
from kvtracker_sdk.errors import ConfigError
from tests.cli.invoke import invoke
from tests.conftest import OnnxExport
from tests.helpers import dev_dependency, openvino_bf16_or_skip
from tests.models.da3.factories import tiny_config as tiny_da3_config
from tests.models.pi3.factories import tiny_config

FAMILIES = ("pi3", "da3")
TINY = {
    "pi3": tiny_config(depth=2),  # one global layer: the smallest Pi3 there is
    "da3": tiny_da3_config(),  # 6 blocks, 2 of them global
}


@pytest.mark.slow
@pytest.mark.parametrize("family", FAMILIES)
def test_export_of_a_checkpoint_prints_its_manifest(
    onnx_exports: Callable[[str], OnnxExport], family: str
) -> None:
    from kvtracker_sdk.backends.onnx_manifest import read_manifest
    from kvtracker_sdk.backends.torch_backend import TorchBackend

    export = onnx_exports(family)
    assert export.exit_code == 0
    assert (export.folder / "manifest.json").is_file() and (export.folder / "weights.bin").is_file()
    manifest = read_manifest(export.folder)
    assert export.manifest_json == json.loads(manifest.model_dump_json())
    assert export.manifest_json["family"] == family
    assert export.manifest_json["check_resolution"] == [126, 168]  # the command's default
    torch_info = TorchBackend.from_pretrained(export.weights).info
    assert export.manifest_json["fingerprint"] == torch_info.fingerprint


@pytest.mark.slow
@pytest.mark.parametrize("family", FAMILIES)
def test_random_weights_export_of_a_config_file(
    family: str,
    onnx_exports: Callable[[str], OnnxExport],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import torch

    from kvtracker_sdk.backends.onnx_manifest import read_manifest
    from kvtracker_sdk.backends.torch_backend import TorchBackend
    from kvtracker_sdk.export_onnx import exporter
    from kvtracker_sdk.models.da3 import DepthAnything3
    from kvtracker_sdk.models.pi3 import Pi3

    printed = read_manifest(onnx_exports(family).folder)  # what the spy answers with
    calls: list[dict[str, Any]] = []

    def spy(model: torch.nn.Module, out_dir: Path, **options: Any) -> object:
        calls.append({"model": model, "out_dir": Path(out_dir), **options})
        return printed

    monkeypatch.setattr(exporter, "export_model", spy)
    config = TINY[family]
    (tmp_path / "tiny.json").write_text(config.model_dump_json())
    out = tmp_path / "tiny-onnx"
    result = invoke(
        "export-onnx", "--out", out, "--random-weights", "--config", tmp_path / "tiny.json",
        "--seed", "3", "--check-size", "56x70", "--json",
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout) == json.loads(printed.model_dump_json())
    (call,) = calls
    assert call["out_dir"] == out and call["check_size"] == (56, 70)
    assert call["model"].config == config
    torch.manual_seed(3)  # the export's random weights are the family's network under the seed
    network = Pi3(config) if family == "pi3" else DepthAnything3(config)  # type: ignore[arg-type]
    exported = call["model"].state_dict()
    assert all(torch.equal(value, exported[key]) for key, value in network.state_dict().items())
    fingerprint = TorchBackend(network).info.weights_fingerprint
    assert call["weights_fingerprint"] == fingerprint


def track_four_frames(tmp_path: Path, *options: object) -> list[str]:
    """``kvtracker track`` over 4 random 60 x 80 frames with ``options``: its pose lines."""
    import cv2

    frames = tmp_path / "frames"
    frames.mkdir()
    rng = np.random.default_rng(0)
    for index in range(4):
        cv2.imwrite(str(frames / f"{index:03d}.png"), rng.integers(0, 256, (60, 80, 3), np.uint8))
    result = invoke(
        "track", frames, *options, "--resolution", "224", "--keyframe-interval", "2",
        "--out", tmp_path / "run",
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    lines = (tmp_path / "run" / "trajectory.txt").read_text().splitlines()
    return [line for line in lines if not line.startswith("#")]


@pytest.mark.slow
@pytest.mark.parametrize("family", FAMILIES)
def test_track_with_the_onnx_backend(
    onnx_exports: Callable[[str], OnnxExport], family: str, tmp_path: Path
) -> None:
    out = onnx_exports(family).folder
    poses = track_four_frames(tmp_path, "--backend", "onnx", "--weights", out)
    assert len(poses) == 4  # a pose per frame


@pytest.mark.slow
def test_track_with_the_openvino_backend(
    onnx_exports: Callable[[str], OnnxExport], tmp_path: Path
) -> None:
    dev_dependency("openvino")
    openvino_bf16_or_skip()
    out = onnx_exports("da3").folder
    options = ("--backend", "openvino", "--weights", out, "--dtype", "bfloat16", "--threads", "1")
    assert len(track_four_frames(tmp_path, *options)) == 4  # a pose per frame
    backend = json.loads((tmp_path / "run" / "run.json").read_text())["backend"]
    assert backend["runtime"] == "openvino" and "threads:1" in backend["accelerations"]


def test_usage_errors_exit_with_the_config_code(tmp_path: Path) -> None:
    existing = tmp_path / "existing"
    existing.mkdir()
    cases = [
        ["-o", existing, "--weights", tmp_path / "nothing.safetensors"],  # exists: checked first
        ["-o", tmp_path / "a", "--random-weights"],  # no --config
        ["-o", tmp_path / "b", "--random-weights", "--config", tmp_path / "none.json"],
        ["-o", tmp_path / "c", "--random-weights", "--config", "large", "--check-size", "9"],
    ]  # fmt: skip
    for args in cases:
        result = invoke("export-onnx", *args)
        assert result.exit_code == ExitCode.CONFIG, (args, result.output)
        assert "error:" in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["existing"]


def test_config_names() -> None:
    from kvtracker_sdk.cli.export_onnx import load_config
    from kvtracker_sdk.models.da3 import DA3Config
    from kvtracker_sdk.models.pi3 import Pi3Config

    assert load_config("large") == Pi3Config.large()
    assert load_config("da3-base") == DA3Config.base()
    with pytest.raises(ConfigError, match="preset"):
        load_config("da3-huge")


def test_parse_size() -> None:
    assert parse_size("126x168") == (126, 168) and parse_size("98X140") == (98, 140)
    for text in ("126", "x168", "126x", "a x b", "-14x14"):
        with pytest.raises(ConfigError):
            parse_size(text)

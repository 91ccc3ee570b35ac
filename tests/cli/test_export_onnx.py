"""``kvtracker export-onnx``: a random-weight export of a tiny config, then tracking with it.

One small export per family (~10-20 s each): the command's whole path (config file, random
weights, summary, manifest) and ``kvtracker track --backend onnx`` reading the result.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from kvtracker_sdk.cli.export_onnx import parse_size
from kvtracker_sdk.cli.failures import ExitCode
from kvtracker_sdk.errors import ConfigError
from tests.cli.invoke import invoke
from tests.helpers import dev_dependency
from tests.models.da3.factories import tiny_config as tiny_da3_config
from tests.models.pi3.factories import tiny_config

TINY = {
    "pi3": tiny_config(depth=2),  # one global layer: the smallest Pi3 there is
    "da3": tiny_da3_config(),  # 6 blocks, 2 of them global
}


@pytest.fixture(scope="module", params=sorted(TINY))
def tiny_export(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> tuple[Path, dict[str, object]]:
    dev_dependency("onnxruntime")
    folder = tmp_path_factory.mktemp("cli-onnx")
    config = folder / "tiny.json"
    config.write_text(TINY[request.param].model_dump_json())
    out = folder / "tiny-onnx"
    args = ["export-onnx", "--out", out, "--random-weights", "--config", config, "--seed", "3"]
    result = invoke(*args, "--check-size", "56x70", "--json")
    assert result.exit_code == 0, result.output
    return out, json.loads(result.stdout)


def test_random_weights_export_of_a_config_file(
    tiny_export: tuple[Path, dict[str, object]],
) -> None:
    import torch

    from kvtracker_sdk.backends.torch_backend import TorchBackend
    from kvtracker_sdk.models.da3 import DepthAnything3
    from kvtracker_sdk.models.pi3 import Pi3

    out, manifest = tiny_export
    family = str(manifest["family"])
    config = TINY[family]
    assert (out / "manifest.json").is_file() and (out / "weights.bin").is_file()
    assert type(config).model_validate(manifest["config"]) == config
    assert manifest["check_resolution"] == [56, 70]
    torch.manual_seed(3)  # the export's random weights are the family's network under the seed
    network = Pi3(config) if family == "pi3" else DepthAnything3(config)  # type: ignore[arg-type]
    assert manifest["fingerprint"] == TorchBackend(network).info.fingerprint


def test_track_with_the_onnx_backend(
    tiny_export: tuple[Path, dict[str, object]], tmp_path: Path
) -> None:
    import cv2

    out, _ = tiny_export
    frames = tmp_path / "frames"
    frames.mkdir()
    rng = np.random.default_rng(0)
    for index in range(4):
        cv2.imwrite(str(frames / f"{index:03d}.png"), rng.integers(0, 256, (60, 80, 3), np.uint8))
    result = invoke(
        "track", frames, "--backend", "onnx", "--weights", out, "--resolution", "224",
        "--keyframe-interval", "2", "--out", tmp_path / "run",
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    lines = (tmp_path / "run" / "trajectory.txt").read_text().splitlines()
    assert len([line for line in lines if not line.startswith("#")]) == 4  # a pose per frame


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

"""Manifests: validated before any worker starts, every mistake a ConfigError naming the field."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.scale.manifest import load_manifest

ORBIT = {"name": "orbit", "simulated": {"orbit_frames": 30}}


def _write(tmp_path: Path, document: Any, name: str = "m.json") -> Path:
    path = tmp_path / name
    path.write_text(document if isinstance(document, str) else json.dumps(document))
    return path


def test_relative_paths_resolve_against_the_manifest_folder(tmp_path: Path) -> None:
    document = {
        "model": {"weights": "w/model.safetensors"},
        "configs": {"a": {}, "b": {"resolution": 224}},
        "sequences": [ORBIT, {"name": "real", "source": "seq", "ground_truth": "seq/gt.txt"},
                      {"name": "sim", "simulated": {"ground_truth": "gt.txt"}}],
    }
    manifest = load_manifest(_write(tmp_path, document))
    base = tmp_path.resolve()
    assert manifest.model is not None and manifest.model.weights == str(base / "w/model.safetensors")
    real = manifest.sequences[1]
    assert (real.source, real.ground_truth) == (base / "seq", base / "seq/gt.txt")
    sim = manifest.sequences[2].simulated
    assert sim is not None and sim.ground_truth == base / "gt.txt"
    assert [(s.name, c) for s, c in manifest.tasks()] == [
        ("orbit", "a"), ("orbit", "b"), ("real", "a"), ("real", "b"), ("sim", "a"), ("sim", "b")]
    assert manifest.tracker_config("b").resolution == 224


@pytest.mark.parametrize(
    ("document", "message"),
    [
        ({"sequences": []}, "at least 1"),
        ({"sequences": [ORBIT, ORBIT]}, "unique"),
        ({"sequences": [{"name": "x", "source": "s"}]}, "need a model"),
        ({"sequences": [{"name": "x", "source": "s", "simulated": {"orbit_frames": 3}}]},
         "exactly one of source and simulated"),
        ({"sequences": [{"name": "x", "simulated": {}}]}, "exactly one of ground_truth"),
        ({"sequences": [{"name": "../x", "simulated": {"orbit_frames": 3}}]}, "pattern"),
        ({"sequences": [ORBIT], "configs": {"a": {"resolution": 17}}}, "resolution"),
        ({"sequences": [ORBIT], "surprise": 1}, "surprise"),
        ("[" * 100_000, "not valid JSON"),
        ("{not json", "not valid JSON"),
    ],
)
def test_bad_manifests_are_config_errors(tmp_path: Path, document: Any, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        load_manifest(_write(tmp_path, document))


def test_a_manifest_that_is_not_a_regular_file_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not a regular file"):
        load_manifest(tmp_path)
    with pytest.raises(ConfigError, match="not a regular file"):
        load_manifest(tmp_path / "missing.json")


def test_yaml_manifests_are_read_safely(tmp_path: Path) -> None:
    pytest.importorskip("yaml")
    text = "sequences:\n  - name: orbit\n    simulated: {orbit_frames: 30}\n"
    assert load_manifest(_write(tmp_path, text, "m.yaml")).sequences[0].name == "orbit"
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_manifest(_write(tmp_path, "!!python/object/apply:os.system ['true']", "evil.yaml"))

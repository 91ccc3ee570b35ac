"""The ONNX exporter's refusals and safe writes (manifest, signatures and shared weights of every
family's export: ``test_export_families.py``).

Uses the session's golden export (``golden_onnx_dir``, checked against PyTorch as it was
written); the failure paths replace the expensive steps with fakes.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from kvtracker_sdk.backends.onnx_manifest import OnnxManifest, read_manifest
from kvtracker_sdk.errors import ConfigError, ModelError
from kvtracker_sdk.export_onnx import export_model, export_onnx, exporter
from tests.models.pi3.factories import random_pi3, tiny_config


@pytest.fixture(scope="module")
def manifest(golden_onnx_dir: Path) -> OnnxManifest:
    return read_manifest(golden_onnx_dir)


def test_the_check_refuses_graphs_that_compute_something_else(
    golden_onnx_dir: Path, manifest: OnnxManifest
) -> None:
    other = random_pi3(tiny_config(dim=64, depth=8, head_dim_heads=48), seed=3)  # golden shapes
    with pytest.raises(ModelError, match="disagree with PyTorch on map"):
        exporter._check(other.eval(), golden_onnx_dir, manifest, (126, 168))


def test_existing_folder_is_kept_unless_overwrite(tmp_path: Path) -> None:
    existing = tmp_path / "export"
    existing.mkdir()
    (existing / "keep.txt").write_text("old")
    with pytest.raises(ConfigError, match="overwrite"):  # before looking for the weights
        export_onnx(existing, weights=tmp_path / "missing.safetensors")
    assert (existing / "keep.txt").read_text() == "old"


def test_failed_export_leaves_the_old_folder_and_no_debris(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    existing = tmp_path / "export"
    existing.mkdir()
    (existing / "keep.txt").write_text("old")

    def fail(model: object, graphs: object, folder: Path, **options: object) -> None:
        (folder / "encoder.onnx").write_text("half written")
        raise ModelError("the graphs disagree")

    monkeypatch.setattr(exporter, "_export_into", fail)
    with pytest.raises(ModelError):
        export_model(random_pi3(), existing, overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["export"]
    assert [p.name for p in existing.iterdir()] == ["keep.txt"]


def test_overwrite_replaces_only_with_a_complete_export(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, manifest: OnnxManifest
) -> None:
    existing = tmp_path / "export"
    existing.mkdir()
    (existing / "keep.txt").write_text("old")

    def succeed(model: object, graphs: object, folder: Path, **options: object) -> OnnxManifest:
        (folder / "manifest.json").write_text(json.dumps({"new": True}))
        return manifest

    monkeypatch.setattr(exporter, "_export_into", succeed)
    export_model(random_pi3(), existing, overwrite=True)
    assert sorted(p.name for p in existing.iterdir()) == ["manifest.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["export"]  # old copy removed
    assert oct(existing.stat().st_mode & 0o777) == "0o755"


def test_unexportable_requests_are_refused(tmp_path: Path) -> None:
    model = random_pi3()
    with pytest.raises(ConfigError, match="multiples of 14"):
        export_model(model, tmp_path / "a", check_size=(100, 168))
    with pytest.raises(ConfigError, match="fp32"):
        export_model(random_pi3().set_precision(torch.bfloat16), tmp_path / "b")
    with pytest.raises(ConfigError, match="weights .* or a config"):
        export_onnx(tmp_path / "c")
    with pytest.raises(ModelError, match="Pi3"):
        export_model(torch.nn.Linear(2, 2), tmp_path / "d")  # type: ignore[arg-type]
    assert not list(tmp_path.iterdir())

"""The ONNX export: manifest, graph signatures with dynamic axes, shared weights, safe writes.

Uses the session's golden export (``golden_onnx_dir``, made by ``export_onnx`` and checked
against PyTorch as it was written); the failure paths replace the expensive steps with fakes.
"""

from __future__ import annotations

import json
from pathlib import Path

import onnx
import pytest
import torch

from kvtracker_sdk.backends.onnx_manifest import FAMILY_GRAPHS, OnnxManifest, read_manifest
from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.errors import ConfigError, ModelError
from kvtracker_sdk.export_onnx import export_model, export_onnx, exporter
from kvtracker_sdk.models.pi3 import load_pi3
from tests.export_onnx.signatures import assert_graphs_declare_the_manifest
from tests.helpers import shared_path
from tests.models.pi3.factories import random_pi3, tiny_config


@pytest.fixture(scope="module")
def manifest(golden_onnx_dir: Path) -> OnnxManifest:
    return read_manifest(golden_onnx_dir)


def test_manifest_identity_equals_the_torch_backends(manifest: OnnxManifest) -> None:
    torch_info = TorchBackend.from_pretrained(
        shared_path("golden", "pi3", "weights.safetensors")
    ).info
    assert manifest.fingerprint == torch_info.fingerprint
    assert manifest.cache_layout == torch_info.layout
    assert (manifest.family, manifest.model, manifest.dtype, manifest.opset) == (
        "pi3",
        "pi3-custom",
        "float32",
        exporter.DEFAULT_OPSET,
    )
    golden = load_pi3(shared_path("golden", "pi3", "weights.safetensors")).model.config
    assert manifest.config == golden.model_dump() and manifest.config_hash == golden.config_hash
    assert (manifest.resolution, manifest.check_resolution) == ("dynamic", (126, 168))
    assert set(manifest.exporter) == {"torch", "onnx", "onnxscript", "onnx-ir"}
    # the export-time check: mapping and tracking through ORT against PyTorch, fp32 rounding only
    assert len(manifest.check) == 8 and max(manifest.check.values()) < 1e-4


def test_graph_files_declare_the_manifest_signatures(
    golden_onnx_dir: Path, manifest: OnnxManifest
) -> None:
    assert tuple(manifest.graphs) == FAMILY_GRAPHS["pi3"]
    assert_graphs_declare_the_manifest(golden_onnx_dir, manifest)
    track = manifest.graphs["decoder_track"]
    assert [s.name for s in track.inputs[:4]] == [
        "patch_tokens",
        "past_length",
        "past_key_values.0.key",
        "past_key_values.0.value",
    ]
    assert track.inputs[2].shape == (1, 2, "past_capacity", 32)
    assert manifest.graphs["encoder"].inputs[0].shape == ("frames", 3, "height", "width")
    present = manifest.graphs["decoder_map"].outputs[2]
    assert (present.name, present.shape) == ("present.0.key", (1, 2, "map_tokens", 32))


def test_weights_are_external_and_shared_between_graphs(
    golden_onnx_dir: Path, manifest: OnnxManifest
) -> None:
    referenced: dict[str, set[tuple[int, int]]] = {}
    for name, spec in manifest.graphs.items():
        model = onnx.load(golden_onnx_dir / spec.file, load_external_data=False)
        refs = set()
        for tensor in model.graph.initializer:
            if tensor.data_location == onnx.TensorProto.EXTERNAL:
                entry = {item.key: item.value for item in tensor.external_data}
                assert entry["location"] == "weights.bin"
                refs.add((int(entry["offset"]), int(entry["length"])))
            else:  # only small tensors stay inline
                assert len(tensor.raw_data) < 1024, (name, tensor.name)
        referenced[name] = refs
    # the tracking decoder's weights are the mapping decoder's: stored once
    assert referenced["decoder_track"] <= referenced["decoder_map"]
    size = (golden_onnx_dir / "weights.bin").stat().st_size
    assert size == manifest.weights_bytes
    assert size < sum(length for refs in referenced.values() for _, length in refs)
    assert all(offset + length <= size for refs in referenced.values() for offset, length in refs)


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

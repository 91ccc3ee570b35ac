"""Every family's export (the session's, ``onnx_exports``): its manifest names the function the
PyTorch backend computes, its graph files declare the manifest's signatures with dynamic axes, and
its weights are external and shared between graphs."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import onnx
import pytest

from kvtracker_sdk.backends.onnx_manifest import FAMILY_GRAPHS, OnnxManifest, read_manifest
from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.export_onnx import exporter
from kvtracker_sdk.models.registry import load_model
from tests.conftest import OnnxExport
from tests.export_onnx.signatures import assert_graphs_declare_the_manifest

# per family: (model name, extra tokens per frame, [(graph, "inputs"/"outputs", index, name, shape)])
EXPECTED: dict[str, tuple[str, int, list[tuple[str, str, int, str, tuple[int | str, ...]]]]] = {
    "pi3": ("pi3-custom", 5, [
        ("decoder_track", "inputs", 0, "patch_tokens", (1, "grid_h", "grid_w", 64)),
        ("decoder_track", "inputs", 1, "past_length", ()),
        ("decoder_track", "inputs", 2, "past_key_values.0.key", (1, 2, "past_capacity", 32)),
        ("decoder_track", "inputs", 3, "past_key_values.0.value", (1, 2, "past_capacity", 32)),
        ("encoder", "inputs", 0, "images", ("frames", 3, "height", "width")),
        ("decoder_map", "outputs", 2, "present.0.key", (1, 2, "map_tokens", 32)),
    ]),
    "da3": ("da3-custom", 1, [
        ("decoder_map", "outputs", 0, "camera_tokens", ("frames", 256)),
        ("decoder_map", "outputs", 4, "features.3", ("frames", "grid_h", "grid_w", 256)),
        ("decoder_map", "outputs", 12, "present.3.value", (1, 2, "map_tokens", 64)),
        ("head_depth", "inputs", 0, "features.0", ("frames", "grid_h", "grid_w", 256)),
        ("head_depth", "outputs", 0, "depth", ("frames", "height", "width")),
        ("head_depth", "outputs", 1, "depth_conf", ("frames", "height", "width")),
    ]),
}  # fmt: skip


@pytest.fixture(scope="module", params=sorted(EXPECTED))
def export(request: pytest.FixtureRequest, onnx_exports: Callable[[str], OnnxExport]) -> OnnxExport:
    return onnx_exports(str(request.param))


def test_manifest_identity_equals_the_torch_backends(export: OnnxExport) -> None:
    manifest = read_manifest(export.folder)
    torch_info = TorchBackend.from_pretrained(export.weights).info
    assert manifest.fingerprint == torch_info.fingerprint
    assert manifest.cache_layout == torch_info.layout
    name, extra_tokens, _ = EXPECTED[export.family]
    assert (manifest.family, manifest.model, manifest.dtype, manifest.opset) == (
        export.family,
        name,
        "float32",
        exporter.DEFAULT_OPSET,
    )
    assert manifest.extra_tokens_per_frame == extra_tokens == torch_info.extra_tokens_per_frame
    config = load_model(export.weights).model.config
    assert manifest.config == json.loads(config.model_dump_json())  # JSON: tuples are lists
    assert manifest.config_hash == config.config_hash
    assert (manifest.resolution, manifest.check_resolution) == ("dynamic", (126, 168))
    assert set(manifest.exporter) == {"torch", "onnx", "onnxscript", "onnx-ir"}
    # the export-time check: mapping and tracking through ORT against PyTorch, fp32 rounding only
    assert len(manifest.check) == 8 and max(manifest.check.values()) < 1e-4


def test_graph_files_declare_the_manifest_signatures(export: OnnxExport) -> None:
    manifest = read_manifest(export.folder)
    assert tuple(manifest.graphs) == FAMILY_GRAPHS[export.family]
    assert_graphs_declare_the_manifest(export.folder, manifest)
    for graph, side, index, name, shape in EXPECTED[export.family][2]:
        spec = getattr(manifest.graphs[graph], side)[index]
        assert (spec.name, spec.shape) == (name, shape), (graph, side, index)


def _external_refs(folder: Path, manifest: OnnxManifest) -> dict[str, set[tuple[int, int]]]:
    """Per graph, the (offset, length) of each external tensor (all in ``weights.bin``)."""
    referenced: dict[str, set[tuple[int, int]]] = {}
    for name, spec in manifest.graphs.items():
        model = onnx.load(folder / spec.file, load_external_data=False)
        refs = set()
        for tensor in model.graph.initializer:
            if tensor.data_location == onnx.TensorProto.EXTERNAL:
                entry = {item.key: item.value for item in tensor.external_data}
                assert entry["location"] == "weights.bin"
                refs.add((int(entry["offset"]), int(entry["length"])))
            else:  # only small tensors stay inline
                assert len(tensor.raw_data) < 1024, (name, tensor.name)
        referenced[name] = refs
    return referenced


def test_weights_are_external_and_shared_between_graphs(export: OnnxExport) -> None:
    manifest = read_manifest(export.folder)
    referenced = _external_refs(export.folder, manifest)
    # the tracking decoder's weights are the mapping decoder's: stored once
    assert referenced["decoder_track"] and referenced["decoder_track"] <= referenced["decoder_map"]
    size = (export.folder / "weights.bin").stat().st_size
    assert size == manifest.weights_bytes
    assert size < sum(length for refs in referenced.values() for _, length in refs)
    assert all(offset + length <= size for refs in referenced.values() for offset, length in refs)

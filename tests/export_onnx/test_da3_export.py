"""The Depth Anything 3 export: manifest, graph signatures with dynamic axes, shared weights, and
what cannot be exported. Uses the session's golden DA3 export (``golden_da3_onnx_dir``)."""

from __future__ import annotations

from pathlib import Path

import onnx
import pytest
import torch
from torch import nn

from kvtracker_sdk.backends.onnx_manifest import FAMILY_GRAPHS, TensorSpec, read_manifest
from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.errors import ConfigError, ModelError
from kvtracker_sdk.export_onnx import export_model, exporter
from kvtracker_sdk.export_onnx.graph_def import GraphDef
from kvtracker_sdk.models.da3 import DepthAnything3
from tests.export_onnx.signatures import assert_graphs_declare_the_manifest
from tests.helpers import shared_path
from tests.models.da3.factories import random_da3, tiny_config


def test_manifest_identity_and_signatures(golden_da3_onnx_dir: Path) -> None:
    manifest = read_manifest(golden_da3_onnx_dir)
    torch_info = TorchBackend.from_pretrained(
        shared_path("golden", "da3", "weights.safetensors")
    ).info
    assert (manifest.family, manifest.model) == ("da3", "da3-custom")
    assert manifest.fingerprint == torch_info.fingerprint
    assert manifest.cache_layout == torch_info.layout and manifest.extra_tokens_per_frame == 1
    assert len(manifest.check) == 8 and max(manifest.check.values()) < 1e-4
    assert tuple(manifest.graphs) == FAMILY_GRAPHS["da3"]
    assert_graphs_declare_the_manifest(golden_da3_onnx_dir, manifest)
    outputs = {s.name: s.shape for s in manifest.graphs["decoder_map"].outputs}
    assert outputs["camera_tokens"] == ("frames", 256)
    assert outputs["features.3"] == ("frames", "grid_h", "grid_w", 256)
    assert outputs["present.3.value"] == (1, 2, "map_tokens", 64)
    assert [s.name for s in manifest.graphs["head_depth"].inputs] == [
        f"features.{level}" for level in range(4)
    ]
    assert [s.shape for s in manifest.graphs["head_depth"].outputs] == [
        ("frames", "height", "width")
    ] * 2


def test_tracking_decoder_shares_the_mapping_decoders_weights(golden_da3_onnx_dir: Path) -> None:
    def external(graph: str) -> set[tuple[str, str]]:
        model = onnx.load(golden_da3_onnx_dir / f"{graph}.onnx", load_external_data=False)
        return {
            (entry["offset"], entry["length"])
            for tensor in model.graph.initializer
            if tensor.data_location == onnx.TensorProto.EXTERNAL
            for entry in [{item.key: item.value for item in tensor.external_data}]
        }

    track, mapping = external("decoder_track"), external("decoder_map")
    assert track and track <= mapping


def test_unexportable_da3_models_are_refused(tmp_path: Path) -> None:
    early = random_da3(tiny_config(out_layers=(1, 3, 4, 5)))  # a head reads block 1 < alt_start 2
    with pytest.raises(ConfigError, match="out_layers"):
        export_model(early, tmp_path / "a")
    with pytest.raises(ConfigError, match="fp32"):
        export_model(random_da3().set_precision(torch.bfloat16), tmp_path / "b")
    assert not list(tmp_path.iterdir())


class _SizeInPython(nn.Module):
    """Computes on a size in Python: the exporter silently fixes it to the example's value."""

    def __init__(self, _: object) -> None:
        super().__init__()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + torch.linspace(0.0, 1.0, x.shape[1])


def test_an_export_that_fixed_a_dynamic_size_is_refused() -> None:
    graph = GraphDef(
        "probe",
        _SizeInPython,
        (TensorSpec(name="x", shape=("frames", "grid_w")),),
        (TensorSpec(name="y", shape=("frames", "grid_w")),),
    )
    model = random_da3()
    assert isinstance(model, DepthAnything3)
    with pytest.raises(ModelError, match="fixed"):
        exporter._export_graph(model, graph, (torch.rand(2, 5),), exporter.DEFAULT_OPSET)

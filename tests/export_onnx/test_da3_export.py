"""What of Depth Anything 3 cannot be exported, and the exporter's refusal of a graph whose
dynamic size came out fixed (manifest, signatures and shared weights: ``test_export_families.py``)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch import nn

from kvtracker_sdk.backends.onnx_manifest import TensorSpec
from kvtracker_sdk.errors import ConfigError, ModelError
from kvtracker_sdk.export_onnx import export_model, exporter
from kvtracker_sdk.export_onnx.graph_def import GraphDef
from kvtracker_sdk.models.da3 import DepthAnything3
from tests.models.da3.factories import random_da3, tiny_config


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

"""Which graphs a network exports to, by family (``pi3_specs.py`` / ``da3_specs.py``)."""

from __future__ import annotations

from typing import Any

from torch import nn

from kvtracker_sdk.errors import ConfigError, ModelError
from kvtracker_sdk.export_onnx import da3_specs, pi3_specs
from kvtracker_sdk.export_onnx.graph_def import GraphDef
from kvtracker_sdk.models.da3 import DepthAnything3
from kvtracker_sdk.models.pi3 import Pi3

__all__ = ["example_inputs", "graphs_of"]


def graphs_of(model: nn.Module) -> list[GraphDef]:
    """The graphs of ``model``'s export; ``ModelError`` for other networks, ``ConfigError`` for
    a DA3 whose heads read a block before ``alt_start`` (no official configuration does; the
    exported encoder would have to output it)."""
    if isinstance(model, Pi3):
        return pi3_specs.pi3_graphs(model.config)
    if isinstance(model, DepthAnything3):
        vit = model.config.backbone
        if min(vit.out_layers) < vit.alt_start:
            raise ConfigError(
                f"ONNX export needs DA3 out_layers >= alt_start ({vit.out_layers}, {vit.alt_start})"
            )
        return da3_specs.da3_graphs(model.config)
    raise ModelError(f"ONNX export supports Pi3 and DepthAnything3 models, got {type(model).__name__}")


def example_inputs(model: nn.Module, size: tuple[int, int]) -> dict[str, tuple[Any, ...]]:
    """Example arguments of every graph at ``size`` (H, W), computed with PyTorch."""
    if isinstance(model, Pi3):
        return pi3_specs.example_inputs(model, size)
    if isinstance(model, DepthAnything3):
        return da3_specs.example_inputs(model, size)
    raise ModelError(f"ONNX export supports Pi3 and DepthAnything3 models, got {type(model).__name__}")

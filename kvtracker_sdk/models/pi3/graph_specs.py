"""The Pi3 graphs as data: ``pi3_graphs(config)`` lists every graph of an export in the order
they run (``graph_def.GraphDef``), and ``example_inputs(model, size)`` computes with PyTorch the
example arguments of every graph.
"""

from __future__ import annotations

from typing import Any

from kvtracker_sdk.models.graph_io import (
    GraphDef,
    TensorSpec,
    encoder_def,
    example_pass,
    past_length_spec,
    past_specs,
    patch_tokens,
    present_specs,
)
from kvtracker_sdk.models.pi3.config import Pi3Config
from kvtracker_sdk.models.pi3.graphs import (
    CameraHeadGraph,
    ConfHeadGraph,
    DecoderMapGraph,
    DecoderTrackGraph,
    EncoderGraph,
    PointsHeadGraph,
)
from kvtracker_sdk.models.pi3.model import Pi3

__all__ = ["example_inputs", "pi3_graphs"]


def _hidden(frames: int | str, dim: int, registers: int) -> tuple[TensorSpec, TensorSpec]:
    return (
        TensorSpec(name="hidden_registers", shape=(frames, registers, 2 * dim)),
        TensorSpec(name="hidden_patches", shape=(frames, "grid_h", "grid_w", 2 * dim)),
    )


def pi3_graphs(config: Pi3Config) -> list[GraphDef]:
    """Every graph of a Pi3 export (their meaning: ``backends/onnx_manifest.py``)."""
    dim = config.decoder.embed_dim
    registers = config.decoder.num_register_tokens
    heads, head_dim = config.decoder.num_heads, config.decoder.head_dim
    layers = len(config.decoder.global_block_indices)
    patches, query_patches = patch_tokens("frames", dim), patch_tokens(1, dim)
    hidden = _hidden("frames", dim, registers)
    present = present_specs(layers, heads, head_dim)
    past = past_specs(layers, heads, head_dim)
    return [
        encoder_def(EncoderGraph, dim),
        GraphDef("decoder_map", DecoderMapGraph, (patches,), (*hidden, *present)),
        GraphDef(
            "decoder_track",
            DecoderTrackGraph,
            (query_patches, past_length_spec(), *past),
            _hidden(1, dim, registers),
        ),
        GraphDef(
            "head_camera",
            CameraHeadGraph,
            hidden,
            (
                TensorSpec(name="rotation_raw", shape=("frames", 9)),
                TensorSpec(name="translation", shape=("frames", 3)),
            ),
        ),
        GraphDef(
            "head_conf",
            ConfHeadGraph,
            hidden,
            (TensorSpec(name="conf_logits", shape=("frames", "height", "width")),),
        ),
        GraphDef(
            "head_points",
            PointsHeadGraph,
            hidden,
            (TensorSpec(name="local_points", shape=("frames", "height", "width", 3)),),
        ),
    ]


def example_inputs(model: Pi3, size: tuple[int, int], *, seed: int = 0) -> dict[str, tuple[Any, ...]]:
    """Forward arguments of every graph at ``size`` = (H, W) (``graph_def.example_pass``)."""
    layers = len(model.config.decoder.global_block_indices)
    example = example_pass(EncoderGraph(model), DecoderMapGraph(model), layers, size, seed)
    hidden = example.head_inputs  # (hidden_registers, hidden_patches)
    return {
        "encoder": (example.images,),
        "decoder_map": (example.keyframe_patches,),
        "decoder_track": example.track_args,
        "head_camera": hidden,
        "head_conf": hidden,
        "head_points": hidden,
    }

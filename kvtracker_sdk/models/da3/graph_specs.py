"""The Depth Anything 3 graphs as data: ``da3_graphs(config)`` lists every graph of an export in
the order they run (``graph_def.GraphDef``), and ``example_inputs(model, size)`` computes with
PyTorch the example arguments of every graph.
"""

from __future__ import annotations

from typing import Any

from kvtracker_sdk.models.da3.config import DA3Config
from kvtracker_sdk.models.da3.graphs import (
    NUM_FEATURE_LEVELS,
    CameraHeadGraph,
    DecoderMapGraph,
    DecoderTrackGraph,
    DepthHeadGraph,
    EncoderGraph,
)
from kvtracker_sdk.models.da3.model import DepthAnything3
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

__all__ = ["da3_graphs", "example_inputs"]


def _head_inputs(frames: int | str, dim: int) -> tuple[TensorSpec, ...]:
    """The decoders' outputs that the heads read: camera tokens, then the four feature levels."""
    return (
        TensorSpec(name="camera_tokens", shape=(frames, 2 * dim)),
        *(
            TensorSpec(name=f"features.{level}", shape=(frames, "grid_h", "grid_w", 2 * dim))
            for level in range(NUM_FEATURE_LEVELS)
        ),
    )


def da3_graphs(config: DA3Config) -> list[GraphDef]:
    """Every graph of a DA3 export (their meaning: ``backends/onnx_manifest.py``)."""
    vit = config.backbone
    dim, heads, head_dim = vit.embed_dim, vit.num_heads, vit.head_dim
    layers = len(vit.global_block_indices)
    patches, query_patches = patch_tokens("frames", dim), patch_tokens(1, dim)
    head_inputs = _head_inputs("frames", dim)
    return [
        encoder_def(EncoderGraph, dim),
        GraphDef(
            "decoder_map",
            DecoderMapGraph,
            (patches,),
            (*head_inputs, *present_specs(layers, heads, head_dim)),
        ),
        GraphDef(
            "decoder_track",
            DecoderTrackGraph,
            (
                query_patches,
                past_length_spec(),
                *past_specs(layers, heads, head_dim),
            ),
            _head_inputs(1, dim),
        ),
        GraphDef(
            "head_camera",
            CameraHeadGraph,
            head_inputs[:1],
            (TensorSpec(name="pose_enc", shape=("frames", 9)),),
        ),
        GraphDef(
            "head_depth",
            DepthHeadGraph,
            head_inputs[1:],
            (
                TensorSpec(name="depth", shape=("frames", "height", "width")),
                TensorSpec(name="depth_conf", shape=("frames", "height", "width")),
            ),
        ),
    ]


def example_inputs(
    model: DepthAnything3, size: tuple[int, int], *, seed: int = 0
) -> dict[str, tuple[Any, ...]]:
    """Forward arguments of every graph at ``size`` = (H, W) (``graph_def.example_pass``)."""
    layers = len(model.config.backbone.global_block_indices)
    example = example_pass(EncoderGraph(model), DecoderMapGraph(model), layers, size, seed)
    camera_tokens, *features = example.head_inputs
    return {
        "encoder": (example.images,),
        "decoder_map": (example.keyframe_patches,),
        "decoder_track": example.track_args,
        "head_camera": (camera_tokens,),
        "head_depth": tuple(features),
    }

"""The Depth Anything 3 graphs as data: ``da3_graphs(config)`` lists every graph of an export in
the order they run (``graph_def.GraphDef``), and ``example_inputs(model, size)`` computes with
PyTorch the example arguments of every graph.
"""

from __future__ import annotations

from typing import Any

import torch

from kvtracker_sdk.backends.onnx_manifest import TensorSpec
from kvtracker_sdk.export_onnx.da3_graphs import (
    NUM_FEATURE_LEVELS,
    CameraHeadGraph,
    DecoderMapGraph,
    DecoderTrackGraph,
    DepthHeadGraph,
    EncoderGraph,
)
from kvtracker_sdk.export_onnx.graph_def import (
    EXAMPLE_KEYFRAMES,
    GraphDef,
    past_specs,
    present_specs,
)
from kvtracker_sdk.models.da3 import DA3Config, DepthAnything3

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
    """Every graph of a DA3 export (see ``backends/onnx_manifest.py`` for their meaning)."""
    vit = config.backbone
    dim, heads, head_dim = vit.embed_dim, vit.num_heads, vit.head_dim
    layers = len(vit.global_block_indices)
    patches = TensorSpec(name="patch_tokens", shape=("frames", "grid_h", "grid_w", dim))
    query_patches = TensorSpec(name="patch_tokens", shape=(1, "grid_h", "grid_w", dim))
    head_inputs = _head_inputs("frames", dim)
    return [
        GraphDef(
            "encoder",
            EncoderGraph,
            (TensorSpec(name="images", shape=("frames", 3, "height", "width")),),
            (patches,),
        ),
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
                TensorSpec(name="past_length", shape=(), dtype="int64"),
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


@torch.no_grad()
def example_inputs(
    model: DepthAnything3, size: tuple[int, int], *, seed: int = 0
) -> dict[str, tuple[Any, ...]]:
    """Forward arguments of every graph for ``EXAMPLE_KEYFRAMES`` keyframes and one query of
    ``size`` = (H, W), computed with PyTorch from seeded random images.

    The tracking decoder's past has one frame of spare capacity beyond ``past_length`` (as a
    ``KVCache`` buffer has), so that the export keeps the two sizes apart.
    """
    generator = torch.Generator().manual_seed(seed)
    images = torch.rand(EXAMPLE_KEYFRAMES + 1, 3, *size, generator=generator)
    encoder = EncoderGraph(model)
    keyframe_patches = encoder(images[:EXAMPLE_KEYFRAMES])
    camera_tokens, *rest = DecoderMapGraph(model)(keyframe_patches)
    features, kv = rest[:NUM_FEATURE_LEVELS], rest[NUM_FEATURE_LEVELS:]
    tokens_per_frame = kv[0].shape[2] // EXAMPLE_KEYFRAMES
    past = tuple(torch.cat((t, t[:, :, :tokens_per_frame]), dim=2) for t in kv)
    return {
        "encoder": (images[:EXAMPLE_KEYFRAMES],),
        "decoder_map": (keyframe_patches,),
        "decoder_track": (encoder(images[EXAMPLE_KEYFRAMES:]), torch.tensor(kv[0].shape[2]), past),
        "head_camera": (camera_tokens,),
        "head_depth": tuple(features),
    }

"""A graph of an export as data: the module computing it, its named inputs and outputs.

Dims are ints (fixed by the architecture) or names (dynamic axes); the same names appear in the
``.onnx`` files and in ``manifest.json``. ``dynamic_shapes`` turns them into ``torch.export``
dims. Both families' graph lists (``pi3_specs.py``, ``da3_specs.py``) are built from these.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from kvtracker_sdk.backends.onnx_manifest import (
    TensorSpec,
    past_key_name,
    past_value_name,
    present_key_name,
    present_value_name,
)

__all__ = [
    "EXAMPLE_KEYFRAMES",
    "ExamplePass",
    "GraphDef",
    "dynamic_shapes",
    "encoder_def",
    "example_pass",
    "past_specs",
    "patch_tokens",
    "present_specs",
]

EXAMPLE_KEYFRAMES = 2  # frames of the export's example inputs (not 1: torch.export would fix it)


@dataclass(frozen=True)
class GraphDef:
    """One graph: the module computing it (built from the loaded network) and its flattened
    inputs and outputs."""

    name: str
    module: Callable[[Any], nn.Module]
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]


def patch_tokens(frames: int | str, dim: int) -> TensorSpec:
    """The encoder's output and the decoders' input: ``patch_tokens`` [frames, h, w, dim]."""
    return TensorSpec(name="patch_tokens", shape=(frames, "grid_h", "grid_w", dim))


def encoder_def(module: Callable[[Any], nn.Module], dim: int) -> GraphDef:
    """The ``encoder`` graph of either family: images [F, 3, H, W] -> patch tokens."""
    images = TensorSpec(name="images", shape=("frames", 3, "height", "width"))
    return GraphDef("encoder", module, (images,), (patch_tokens("frames", dim),))


def present_specs(layers: int, heads: int, head_dim: int) -> tuple[TensorSpec, ...]:
    """The mapping decoder's K/V outputs: ``present.{i}.key``, ``present.{i}.value``, ..."""
    return tuple(
        TensorSpec(name=name(i), shape=(1, heads, "map_tokens", head_dim))
        for i in range(layers)
        for name in (present_key_name, present_value_name)
    )


def past_specs(layers: int, heads: int, head_dim: int) -> tuple[TensorSpec, ...]:
    """The tracking decoder's cache inputs: ``past_key_values.{i}.key``, ``.value``, ..."""
    return tuple(
        TensorSpec(name=name(i), shape=(1, heads, "past_capacity", head_dim))
        for i in range(layers)
        for name in (past_key_name, past_value_name)
    )


def dynamic_shapes(graph: GraphDef, patch_size: int) -> tuple[Any, ...]:
    """``torch.export`` dynamic shapes of the graph's forward arguments.

    One ``Dim`` per dim name; "height"/"width" are ``patch_size`` times the grid dims, so the
    exporter knows H and W divide exactly into patches.
    """
    dims: dict[str, Any] = {}

    def dim(name: str) -> Any:
        if name in ("height", "width"):
            return patch_size * dim("grid_h" if name == "height" else "grid_w")
        if name not in dims:
            dims[name] = torch.export.Dim(name)
        return dims[name]

    per_input = [
        {axis: dim(size) for axis, size in enumerate(spec.shape) if isinstance(size, str)} or None
        for spec in graph.inputs
    ]
    if graph.name == "decoder_track":  # forward(patch_tokens, past_length, past: tuple)
        return (per_input[0], per_input[1], tuple(per_input[2:]))
    return tuple(per_input)


@dataclass(frozen=True)
class ExamplePass:
    """Example arguments shared by both families' graphs (computed with PyTorch)."""

    images: torch.Tensor  # [EXAMPLE_KEYFRAMES, 3, H, W]: the encoder's example
    keyframe_patches: torch.Tensor  # the mapping decoder's example
    head_inputs: tuple[torch.Tensor, ...]  # the mapping decoder's outputs before its K/V
    track_args: tuple[Any, ...]  # (query patch tokens, past_length, past K/V tuple)


@torch.no_grad()
def example_pass(
    encoder: nn.Module, decoder_map: nn.Module, layers: int, size: tuple[int, int], seed: int
) -> ExamplePass:
    """Encode ``EXAMPLE_KEYFRAMES`` keyframes and one query of ``size`` = (H, W) (seeded random
    images), map the keyframes, and build the tracking decoder's past from their K/V.

    The past has one frame of spare capacity beyond ``past_length`` (as a ``KVCache`` buffer
    has), so that the export keeps the two sizes apart.
    """
    generator = torch.Generator().manual_seed(seed)
    images = torch.rand(EXAMPLE_KEYFRAMES + 1, 3, *size, generator=generator)
    keyframe_patches = encoder(images[:EXAMPLE_KEYFRAMES])
    outputs = decoder_map(keyframe_patches)
    head_inputs, kv = outputs[: len(outputs) - 2 * layers], outputs[len(outputs) - 2 * layers :]
    tokens_per_frame = kv[0].shape[2] // EXAMPLE_KEYFRAMES
    past = tuple(torch.cat((t, t[:, :, :tokens_per_frame]), dim=2) for t in kv)
    query = encoder(images[EXAMPLE_KEYFRAMES:])
    return ExamplePass(
        images=images[:EXAMPLE_KEYFRAMES],
        keyframe_patches=keyframe_patches,
        head_inputs=tuple(head_inputs),
        track_args=(query, torch.tensor(kv[0].shape[2]), past),
    )

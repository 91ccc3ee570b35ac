"""A network cut into graphs, as data: each graph's module and its named inputs and outputs.

Every family's record lists its graphs (``ModelFamily.graphs``): the modules are thin views over
the loaded network that run its own stages, so an exported graph computes what the PyTorch pass
computes. Nothing here needs ONNX: ``export_onnx/`` turns these into ``.onnx`` files and
``backends/onnx_manifest.py`` writes the specs into ``manifest.json``.

Dims are ints (fixed by the architecture) or names (dynamic axes: ``frames``, ``grid_h``,
``grid_w``, ``height``, ``width``, ``map_tokens``, ``past_capacity``); the same names appear in the
``.onnx`` files and the manifest.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from pydantic import BaseModel, ConfigDict
from torch import nn

__all__ = [
    "EXAMPLE_KEYFRAMES",
    "ExamplePass",
    "GraphDef",
    "TensorSpec",
    "encoder_def",
    "example_pass",
    "past_key_name",
    "past_length_spec",
    "past_specs",
    "past_value_name",
    "patch_tokens",
    "present_key_name",
    "present_specs",
    "present_value_name",
]

EXAMPLE_KEYFRAMES = 2  # frames of the export's example inputs (not 1: torch.export would fix it)


class TensorSpec(BaseModel):
    """One graph input or output: dims are ints (fixed) or names (dynamic axes)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    shape: tuple[int | str, ...]
    dtype: str = "float32"


@dataclass(frozen=True)
class GraphDef:
    """One graph: the module computing it (built from the loaded network) and its flattened
    inputs and outputs."""

    name: str
    module: Callable[[Any], nn.Module]
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]


def past_key_name(layer: int) -> str:
    return f"past_key_values.{layer}.key"


def past_value_name(layer: int) -> str:
    return f"past_key_values.{layer}.value"


def present_key_name(layer: int) -> str:
    return f"present.{layer}.key"


def present_value_name(layer: int) -> str:
    return f"present.{layer}.value"


def patch_tokens(frames: int | str, dim: int) -> TensorSpec:
    """The encoder's output and the decoders' input: ``patch_tokens`` [frames, h, w, dim]."""
    return TensorSpec(name="patch_tokens", shape=(frames, "grid_h", "grid_w", dim))


def encoder_def(module: Callable[[Any], nn.Module], dim: int) -> GraphDef:
    """The ``encoder`` graph of every family: images [F, 3, H, W] -> patch tokens."""
    images = TensorSpec(name="images", shape=("frames", 3, "height", "width"))
    return GraphDef("encoder", module, (images,), (patch_tokens("frames", dim),))


def present_specs(layers: int, heads: int, head_dim: int) -> tuple[TensorSpec, ...]:
    """The mapping decoder's K/V outputs: ``present.{i}.key``, ``present.{i}.value``, ..."""
    return tuple(
        TensorSpec(name=name(i), shape=(1, heads, "map_tokens", head_dim))
        for i in range(layers)
        for name in (present_key_name, present_value_name)
    )


def past_length_spec() -> TensorSpec:
    """The tracking decoder's number of cached tokens: int64 []."""
    return TensorSpec(name="past_length", shape=(), dtype="int64")


def past_specs(layers: int, heads: int, head_dim: int) -> tuple[TensorSpec, ...]:
    """The tracking decoder's cache inputs: ``past_key_values.{i}.key``, ``.value``, ..."""
    return tuple(
        TensorSpec(name=name(i), shape=(1, heads, "past_capacity", head_dim))
        for i in range(layers)
        for name in (past_key_name, past_value_name)
    )


@dataclass(frozen=True)
class ExamplePass:
    """Example arguments shared by every family's graphs (computed with PyTorch)."""

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

"""A global block attending over a past K/V input: the tracking decoders' step, in ONNX form.

``Block.forward_track`` writes the query's K/V into a cache buffer in place, which ONNX cannot
express; an exported tracking graph instead receives each cached layer's buffers as inputs and
reads tokens ``[:past_length]`` of them. Both families' tracking graphs use this step.
"""

from __future__ import annotations

import torch

from kvtracker_sdk.models.layers.block import Block
from kvtracker_sdk.models.layers.rope2d import RopeTable

__all__ = ["attend_past"]


def attend_past(
    block: Block,
    x: torch.Tensor,
    rope: RopeTable,
    past_key: torch.Tensor,
    past_value: torch.Tensor,
    past_length: torch.Tensor,
) -> torch.Tensor:
    """A global block for one frame ``x`` [1, T, dim] over ``past[:, :, :past_length]`` + itself.

    The same computation as ``Block.forward_track`` (pre-norm attention, LayerScale, MLP), with
    the cache read by slicing instead of written in place. The attention is spelled out
    (softmax(q kᵀ / sqrt(d)) v) rather than ``F.scaled_dot_product_attention``: ONNX Runtime
    then folds the key transpose into its MatMul, 15% faster at 32 keyframes than the
    exporter's decomposition of SDPA.
    """
    attn = block.attn
    q, k, v = attn.project(block.norm1(x), rope)  # [1, heads, T, head_dim] each
    keys = torch.cat((past_key[:, :, :past_length], k), dim=2)  # [1, heads, past + T, head_dim]
    values = torch.cat((past_value[:, :, :past_length], v), dim=2)
    scores = torch.matmul(q * q.shape[-1] ** -0.5, keys.transpose(-1, -2))  # [1, heads, T, past + T]
    attended = torch.matmul(torch.softmax(scores, dim=-1), values)
    x = x + block.ls1(attn.proj(attended.transpose(1, 2).flatten(2)))  # [1, T, dim]
    return x + block.ls2(block.mlp(block.norm2(x)))

"""The alternating frame / global attention stack with a KV cache: shared by every family.

Pi3's decoder and DA3's backbone (from ``alt_start`` on) are the same machine: blocks at even
indices attend within each frame ([B*N, T, C]), blocks at odd indices attend over all frames of a
sequence ([B, N*T, C], frame-major) — the only places where frames interact, and the layers a KV
cache stores. The heads read, at each tapped block ``l``, ``cat(last per-frame output, output of
l)`` [B, N, T, 2C] (Pi3 taps its last block; DA3 its ``out_layers``).

What differs between the passes is only the **global step** (ordinal among the global blocks,
block, tokens [B, N*T, C]) -> tokens:

- ``FullStep``: plain attention, optionally under a boolean mask (``keyframe_query_mask``);
- ``KVRecordingStep``: the mapping pass; also keeps every global block's K (after k_norm and
  RoPE) and V [B, heads, N*T, head_dim] — what a ``KVCache`` stores;
- ``CacheTrackingStep``: F independent query frames against a cache; each writes its K/V into
  the cache's scratch after the layer's cached tokens (``cache.layer_length``: a pruned cache's
  layers differ) and attends over the cached tokens plus its own
  (``Block.forward_track``). The cache is checked **before** it grows, and the mask of several
  queries is built for their rows only ([F*T, past + F*T], not the S x S matrix). A cache with
  ``key_mask(layer)`` (bool per buffer token, True = may attend, or None for all: a
  static-shape cache whose "length" is its fixed capacity) masks the tokens it does not hold;
- ``PastInputsStep``: the exported tracking graphs' step, one frame reading each layer's past
  K/V from graph inputs by slicing (``Block.forward_past``; ONNX cannot write in place).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence
from typing import cast

import torch
from torch import nn

from kvtracker_sdk.models.layers.attention import CacheBuffers, keyframe_query_mask
from kvtracker_sdk.models.layers.block import Block
from kvtracker_sdk.models.layers.cache_layout import CacheLayout
from kvtracker_sdk.models.layers.rope2d import RopeTable

__all__ = [
    "CacheTrackingStep",
    "FullStep",
    "GlobalStep",
    "KVRecordingStep",
    "PastInputsStep",
    "run_alternating",
]

# (ordinal among global blocks, block, tokens [B, N*T, C]) -> tokens [B, N*T, C]
GlobalStep = Callable[[int, Block, torch.Tensor], torch.Tensor]


def run_alternating(
    x: torch.Tensor,
    blocks: nn.ModuleList,
    *,
    start: int,
    local_rope: RopeTable | None,
    global_step: GlobalStep,
    taps: Collection[int],
) -> list[torch.Tensor]:
    """Blocks ``start`` on over ``x`` [B, N, T, C] (even index: per frame, odd: ``global_step``).

    Returns, for every index in ``taps`` in block order, ``cat(last per-frame output, output of
    that block)`` [B, N, T, 2C]. ``local_rope``: one frame's table [T, head_dim] for the
    per-frame blocks (the global step holds its own).
    """
    batch, frames, length, dim = x.shape
    local_x = x  # the output of the last per-frame block (the left half of a tap)
    taken = []
    for index in range(start, len(blocks)):
        block = cast(Block, blocks[index])
        if index % 2 == 1:  # global: [B, N*T, C]
            x = global_step((index - start) // 2, block, x.reshape(batch, frames * length, dim))
            x = x.reshape(batch, frames, length, dim)
        else:  # per frame: [B*N, T, C]
            flat = x.reshape(batch * frames, length, dim)
            x = local_x = block(flat, rope=local_rope).reshape(batch, frames, length, dim)
        if index in taps:
            taken.append(torch.cat((local_x, x), dim=-1))
    return taken


class FullStep:
    """Full attention over every frame of a sequence, under ``attn_mask`` if given."""

    def __init__(self, rope: RopeTable | None, attn_mask: torch.Tensor | None = None) -> None:
        self.rope = rope  # [N*T, head_dim]
        self.attn_mask = attn_mask  # bool [N*T, N*T], True = may attend

    def __call__(self, ordinal: int, block: Block, x: torch.Tensor) -> torch.Tensor:
        return block(x, rope=self.rope, attn_mask=self.attn_mask)


class KVRecordingStep:
    """The mapping pass: ``Block.forward_map`` with one RoPE table, keeping every global block's
    K/V in order (what a ``KVCache`` stores)."""

    def __init__(self, rope: RopeTable | None) -> None:
        self.rope = rope
        self.keys: list[torch.Tensor] = []
        self.values: list[torch.Tensor] = []

    def __call__(self, ordinal: int, block: Block, x: torch.Tensor) -> torch.Tensor:
        out, k, v = block.forward_map(x, rope=self.rope)
        self.keys.append(k)
        self.values.append(v)
        return out


class CacheTrackingStep:
    """F independent query frames of T tokens each against ``cache`` (one sequence [1, F*T, C]).

    Construction checks the cache against ``layout`` (``CacheError`` leaves it untouched), then
    grows it to hold the queries' scratch. ``rope``: one frame's global table [T, head_dim].
    """

    def __init__(
        self,
        cache: CacheBuffers,
        layout: CacheLayout,
        *,
        frames: int,
        tokens_per_frame: int,
        rope: RopeTable | None,
        dtype: torch.dtype,
        device: torch.device,
    ) -> None:
        layout.check_cache(cache, dtype=dtype, device=device)  # before touching it
        self.cache = cache
        self.past = [cache.layer_length(i) for i in range(layout.num_layers)]
        cache.ensure_capacity(cache.length + frames * tokens_per_frame)
        self.rope = None if rope is None else rope.repeat(frames)
        # one frame sees every cached token and itself: no mask. Several: [F*T, past + F*T],
        # the query rows only, one per distinct layer length
        self.masks: dict[int, torch.Tensor | None] = {
            past: None
            if frames == 1
            else keyframe_query_mask(past, frames, tokens_per_frame, queries_only=True, device=device)
            for past in set(self.past)
        }
        # a static-shape cache (backends/cuda_graph_step.py) holds garbage between its content
        # and its fixed scratch: it says per layer which of its tokens may be attended to
        key_mask = getattr(cache, "key_mask", None)
        self.layer_masks: list[torch.Tensor | None] | None = None
        if key_mask is not None:
            own = frames * tokens_per_frame
            self.layer_masks = []
            for ordinal, past in enumerate(self.past):
                mask, layer_mask = self.masks[past], key_mask(ordinal)  # None: every token
                if layer_mask is not None:
                    valid = layer_mask[: past + own].unsqueeze(0)  # bool [1, past + own]
                    mask = valid if mask is None else mask & valid
                self.layer_masks.append(mask)

    def __call__(self, ordinal: int, block: Block, x: torch.Tensor) -> torch.Tensor:
        key_buffer, value_buffer = self.cache.buffers(ordinal)
        past = self.past[ordinal]
        mask = self.masks[past] if self.layer_masks is None else self.layer_masks[ordinal]
        return block.forward_track(
            x, key_buffer, value_buffer, past, rope=self.rope, attn_mask=mask
        )


class PastInputsStep:
    """One frame against past K/V given as tensors: ``past`` = (key 0, value 0, key 1, ...), each
    [1, heads, capacity >= past_length, head_dim]; tokens after ``past_length`` are ignored."""

    def __init__(
        self, past: Sequence[torch.Tensor], past_length: torch.Tensor, rope: RopeTable | None
    ) -> None:
        self.past = past
        self.past_length = past_length  # int64 [] (a graph input: the cache length is dynamic)
        self.rope = rope  # [T, head_dim]

    def __call__(self, ordinal: int, block: Block, x: torch.Tensor) -> torch.Tensor:
        key, value = self.past[2 * ordinal], self.past[2 * ordinal + 1]
        return block.forward_past(x, key, value, self.past_length, rope=self.rope)

"""Pi3's decoder: blocks alternating frame attention and global (cross-frame) attention.

Tokens arrive as [B, N, T, dim]: B independent sequences of N frames, T = registers + patches per
frame. Even blocks 0, 2, ... attend within each frame (sequence [B*N, T]); odd blocks 1, 3, ...
attend over all frames of a sequence (sequence [B, N*T], frame-major) — the only places where frames
interact, and the layers whose K/V a KV cache stores. Every block uses qk-norm, LayerScale and the
same per-frame RoPE2D positions (no frame index, so a cached key stays valid for any query).

The three passes differ only in the global blocks:

- ``forward``: full attention (optionally under a boolean mask, e.g. ``keyframe_query_mask``);
- ``forward_map``: full attention, also returning each global block's K/V [B, heads, N*T, head_dim];
- ``forward_track``: the frames attend over a cache's keyframe tokens plus their own frame.

The output handed to the heads is concat(second-to-last block out, last block out) [B, N, T, 2*dim].
"""

from __future__ import annotations

from collections.abc import Callable
from typing import cast

import torch
from torch import nn

from kvtracker_sdk.models.layers.attention import (
    CacheBuffers,
    check_cache_buffers,
    keyframe_query_mask,
)
from kvtracker_sdk.models.layers.block import Block, KVRecordingStep
from kvtracker_sdk.models.layers.rope2d import RopeTable
from kvtracker_sdk.models.pi3.config import Pi3DecoderConfig

__all__ = ["Pi3Decoder"]

# (ordinal among global blocks, block, tokens [B, N*T, dim]) -> tokens [B, N*T, dim]
GlobalStep = Callable[[int, Block, torch.Tensor], torch.Tensor]


class Pi3Decoder(nn.ModuleList):
    """The list of decoder blocks (checkpoint names ``decoder.{i}.*``) and the passes over it."""

    def __init__(self, config: Pi3DecoderConfig) -> None:
        super().__init__(
            Block(
                config.embed_dim,
                config.num_heads,
                mlp_ratio=config.mlp_ratio,
                qk_norm=True,
                layerscale_init=0.01,
            )
            for _ in range(config.depth)
        )
        self.num_heads = config.num_heads
        self.head_dim = config.head_dim
        self.global_block_indices = config.global_block_indices

    def _run(self, tokens: torch.Tensor, rope: RopeTable, global_step: GlobalStep) -> torch.Tensor:
        batch, frames, length, dim = tokens.shape
        x = tokens
        last_two = []
        for index, block in enumerate(self):
            if index % 2 == 0:  # frame attention: [B*N, T, dim]
                x = block(x.reshape(batch * frames, length, dim), rope=rope)
            else:  # global attention: [B, N*T, dim]
                x = global_step(
                    index // 2, cast(Block, block), x.reshape(batch, frames * length, dim)
                )
            if index >= len(self) - 2:
                last_two.append(x.reshape(batch, frames, length, dim))
        return torch.cat(last_two, dim=-1)

    def forward(
        self,
        tokens: torch.Tensor,
        rope: RopeTable,
        *,
        global_attn_mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """[B, N, T, dim] -> [B, N, T, 2*dim]; ``rope`` is one frame's table [T, head_dim].

        ``global_attn_mask`` bool [N*T, N*T] (True = may attend) applies to the global blocks.
        """
        global_rope = rope.repeat(tokens.shape[1])
        return self._run(
            tokens, rope, lambda _, block, x: block(x, rope=global_rope, attn_mask=global_attn_mask)
        )

    def forward_map(
        self, tokens: torch.Tensor, rope: RopeTable
    ) -> tuple[torch.Tensor, list[torch.Tensor], list[torch.Tensor]]:
        """``forward`` plus per global block K (after k_norm and RoPE) and V, [B, heads, N*T, head_dim]."""
        step = KVRecordingStep(rope.repeat(tokens.shape[1]))
        return self._run(tokens, rope, step), step.keys, step.values

    def forward_track(
        self, tokens: torch.Tensor, rope: RopeTable, cache: CacheBuffers
    ) -> torch.Tensor:
        """Independent query frames [1, F, T, dim] against ``cache`` -> [1, F, T, 2*dim].

        Each frame's global attention sees the cached tokens and its own T tokens (one SDPA call
        with a block mask when F > 1). The frames' K/V go to the cache's scratch region; the
        cached part is only read.
        """
        frames, length = tokens.shape[1], tokens.shape[2]
        past = cache.length
        self.check_cache(cache, dtype=tokens.dtype, device=tokens.device)  # before touching it
        cache.ensure_capacity(past + frames * length)
        mask = None
        if frames > 1:
            mask = keyframe_query_mask(
                past, frames, length, queries_only=True, device=tokens.device
            )
        global_rope = rope.repeat(frames)

        def step(ordinal: int, block: Block, x: torch.Tensor) -> torch.Tensor:
            key_buffer, value_buffer = cache.buffers(ordinal)
            return block.forward_track(
                x, key_buffer, value_buffer, past, rope=global_rope, attn_mask=mask
            )

        return self._run(tokens, rope, step)

    def check_cache(self, cache: CacheBuffers, *, dtype: torch.dtype, device: torch.device) -> None:
        """Raise ``CacheError`` unless every global layer has buffers of the right shape and dtype."""
        check_cache_buffers(
            cache,
            block_indices=self.global_block_indices,
            num_heads=self.num_heads,
            head_dim=self.head_dim,
            dtype=dtype,
            device=device,
        )

"""Pi3's decoder: blocks alternating frame attention and global (cross-frame) attention.

Tokens arrive as [B, N, T, dim]: B independent sequences of N frames, T = registers + patches per
frame. Even blocks 0, 2, ... attend within each frame (sequence [B*N, T]); odd blocks 1, 3, ...
attend over all frames of a sequence (sequence [B, N*T], frame-major) — the only places where frames
interact, and the layers whose K/V a KV cache stores. Every block uses qk-norm, LayerScale and the
same per-frame RoPE2D positions (no frame index, so a cached key stays valid for any query).

The loop and the global steps are ``models/layers/alternating.py``'s (shared with DA3's backbone
and the exported graphs); the three passes differ only in the global step:

- ``forward``: full attention (optionally under a boolean mask, e.g. ``keyframe_query_mask``);
- ``forward_map``: full attention, also returning each global block's K/V [B, heads, N*T, head_dim];
- ``forward_track``: the frames attend over a cache's keyframe tokens plus their own frame.

The output handed to the heads is concat(second-to-last block out, last block out) [B, N, T, 2*dim].
"""

from __future__ import annotations

import torch
from torch import nn

from kvtracker_sdk.models.layers.alternating import (
    CacheTrackingStep,
    FullStep,
    GlobalStep,
    KVRecordingStep,
    run_alternating,
)
from kvtracker_sdk.models.layers.attention import CacheBuffers
from kvtracker_sdk.models.layers.block import Block
from kvtracker_sdk.models.layers.cache_layout import CacheLayout
from kvtracker_sdk.models.layers.precision import matmul_dtype
from kvtracker_sdk.models.layers.rope2d import RopeTable
from kvtracker_sdk.models.pi3.config import Pi3DecoderConfig

__all__ = ["Pi3Decoder"]


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
        self.layout = CacheLayout(config.global_block_indices, config.num_heads, config.head_dim)
        self.num_heads = config.num_heads
        self.head_dim = config.head_dim
        self.global_block_indices = config.global_block_indices

    def run(self, tokens: torch.Tensor, rope: RopeTable, global_step: GlobalStep) -> torch.Tensor:
        """[B, N, T, dim] -> [B, N, T, 2*dim] with ``global_step`` in the global blocks (the
        exported graphs call this with their own step). ``rope``: one frame's table."""
        (hidden,) = run_alternating(
            tokens, self, start=0, local_rope=rope, global_step=global_step, taps={len(self) - 1}
        )
        return hidden

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
        return self.run(tokens, rope, FullStep(rope.repeat(tokens.shape[1]), global_attn_mask))

    def forward_map(
        self, tokens: torch.Tensor, rope: RopeTable
    ) -> tuple[torch.Tensor, list[torch.Tensor], list[torch.Tensor]]:
        """``forward`` plus per global block K (after k_norm and RoPE) and V, [B, heads, N*T, head_dim]."""
        step = KVRecordingStep(rope.repeat(tokens.shape[1]))
        return self.run(tokens, rope, step), step.keys, step.values

    def forward_track(
        self, tokens: torch.Tensor, rope: RopeTable, cache: CacheBuffers
    ) -> torch.Tensor:
        """Independent query frames [1, F, T, dim] against ``cache`` -> [1, F, T, 2*dim].

        Each frame's global attention sees the cached tokens and its own T tokens (one SDPA call
        with a block mask when F > 1). The frames' K/V go to the cache's scratch region; the
        cached part is only read.
        """
        step = CacheTrackingStep(
            cache,
            self.layout,
            frames=tokens.shape[1],
            tokens_per_frame=tokens.shape[2],
            rope=rope,
            dtype=matmul_dtype(tokens),  # the cache holds K/V in the matrix products' dtype
            device=tokens.device,
        )
        return self.run(tokens, rope, step)

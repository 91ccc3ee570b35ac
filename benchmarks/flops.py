"""Arithmetic (FLOP) model of a Pi3 pass: what a tracking step and a full recompute cost.

Counted: the FLOPs of every matrix product, 2 per multiply-add — the patch-embedding convolution,
every transformer block's qkv / proj / MLP linears and its two attention products (Q·Kᵀ and
A·V, 2·2·L·S·dim for L queries over S keys), the head decoders (``projects``, blocks,
``linear_out``), the camera head's MLPs, the pixel-shuffle heads' linears and the rotation of
local points to world points.

Not counted (they are memory-bound or O(tokens·dim), a few % at most): LayerNorm, GELU, softmax,
RoPE, residual adds, LayerScale, the pos-embed interpolation, the camera head's 3x3 SVD, and the
copy of a tracked frame's K/V into the cache's scratch region. ``torch.utils.flop_counter`` agrees
with this model to the camera head's 3x3 products (the smoke test checks it).

Shapes: a frame of H x W pixels has P = (H/p)·(W/p) patches; the encoder sees 1 + registers + P
tokens, the decoder and the head decoders T = decoder registers + P tokens, the final heads the P
patch tokens. Frame blocks and head decoders attend within a frame (L = S = T); global blocks over
all frames of the pass (recompute on M frames: L = S = M·T) or, in a tracking step of one frame,
from its T tokens over the N·T cached plus its own T tokens (L = T, S = (N+1)·T).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from kvtracker_sdk.models.pi3.config import Pi3Config
from kvtracker_sdk.types import HeadSet

__all__ = ["PassFlops", "block_flops", "recompute_flops", "tracking_step_flops"]


def block_flops(queries: int, keys: int, dim: int, mlp_ratio: float) -> tuple[float, float]:
    """(linear, attention) FLOPs of one pre-norm block: ``queries`` tokens attending to ``keys``.

    Linear: qkv (3·dim²), proj (dim²), MLP (2·ratio·dim²) per query token. Attention: Q·Kᵀ and
    A·V, each 2·queries·keys·dim. (K/V of tokens that are only keys — a cache — cost nothing.)
    """
    linear = 2.0 * queries * dim * dim * (4 + 2 * mlp_ratio)
    attention = 4.0 * queries * keys * dim
    return linear, attention


@dataclass(frozen=True)
class PassFlops:
    """FLOPs of one pass by stage (see the module docstring for what each includes)."""

    encoder: float
    decoder_linear: float
    frame_attention: float
    global_attention: float
    head_decoders: float
    heads: float

    @property
    def total(self) -> float:
        return (
            self.encoder
            + self.decoder_linear
            + self.frame_attention
            + self.global_attention
            + self.head_decoders
            + self.heads
        )

    def to_dict(self) -> dict[str, float]:
        return {**asdict(self), "total": self.total}


def _patches(config: Pi3Config, height: int, width: int) -> int:
    return (height // config.patch_size) * (width // config.patch_size)


def _encoder_per_frame(config: Pi3Config, patches: int) -> float:
    enc = config.encoder
    tokens = 1 + enc.num_register_tokens + patches
    embed = 2.0 * patches * 3 * config.patch_size**2 * enc.embed_dim
    linear, attention = block_flops(tokens, tokens, enc.embed_dim, enc.mlp_ratio)
    return embed + enc.depth * (linear + attention)


def _heads_per_frame(config: Pi3Config, patches: int, heads: HeadSet) -> tuple[float, float]:
    """(head decoders, final heads) FLOPs of one frame for the requested ``heads``."""
    dec, cfg = config.decoder, config.heads
    tokens = dec.num_register_tokens + patches
    linear, attention = block_flops(tokens, tokens, cfg.embed_dim, cfg.mlp_ratio)
    blocks = cfg.depth * (linear + attention) + 2.0 * tokens * 2 * dec.embed_dim * cfg.embed_dim

    def head_decoder(out_dim: int) -> float:
        return blocks + 2.0 * tokens * cfg.embed_dim * out_dim

    cam = cfg.camera_out_dim
    # camera head: 2 residual MLPs of 3 linears per patch token, then 2 linears + fc_t/fc_rot pooled
    decoders = head_decoder(cam)
    final = 2.0 * patches * 6 * cam * cam + 2.0 * (2 * cam * cam + 12 * cam)
    pixels = config.patch_size**2
    if heads is not HeadSet.CAMERA:  # confidence: 1 channel per pixel
        decoders += head_decoder(cfg.point_out_dim)
        final += 2.0 * patches * cfg.point_out_dim * pixels
    if heads is HeadSet.ALL:  # points: 3 channels per pixel, then rotated to the world frame
        decoders += head_decoder(cfg.point_out_dim)
        final += 2.0 * patches * (cfg.point_out_dim * 3 + 9) * pixels
    return decoders, final


def _pass_flops(
    config: Pi3Config, height: int, width: int, frames: int, global_keys: int, heads: HeadSet
) -> PassFlops:
    """``frames`` query frames; each global block's queries attend to ``global_keys`` keys."""
    dec = config.decoder
    patches = _patches(config, height, width)
    tokens = dec.num_register_tokens + patches
    linear, frame_attention = block_flops(tokens, tokens, dec.embed_dim, dec.mlp_ratio)
    _, global_attention = block_flops(frames * tokens, global_keys, dec.embed_dim, dec.mlp_ratio)
    global_blocks = len(dec.global_block_indices)
    decoders, final = _heads_per_frame(config, patches, heads)
    return PassFlops(
        encoder=frames * _encoder_per_frame(config, patches),
        decoder_linear=frames * dec.depth * linear,
        frame_attention=frames * (dec.depth - global_blocks) * frame_attention,
        global_attention=global_blocks * global_attention,
        head_decoders=frames * decoders,
        heads=frames * final,
    )


def tracking_step_flops(
    config: Pi3Config, height: int, width: int, keyframes: int, heads: HeadSet
) -> PassFlops:
    """One frame tracked against ``keyframes`` cached frames: global attention over (N+1)·T keys."""
    tokens = config.decoder.num_register_tokens + _patches(config, height, width)
    return _pass_flops(config, height, width, 1, (keyframes + 1) * tokens, heads)


def recompute_flops(
    config: Pi3Config, height: int, width: int, frames: int, heads: HeadSet
) -> PassFlops:
    """The full forward on ``frames`` frames (N keyframes + the query: frames = N + 1)."""
    tokens = config.decoder.num_register_tokens + _patches(config, height, width)
    return _pass_flops(config, height, width, frames, frames * tokens, heads)

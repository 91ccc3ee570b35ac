"""Multi-head self-attention with optional qk-norm and RoPE2D, usable with a KV cache.

One module, one computation::

    qkv Linear (output channels [q | k | v], head-major inside each)
    -> split into heads                         q, k, v: [B, heads, L, head_dim]
    -> q_norm(q), k_norm(k)                     optional LayerNorm over head_dim, shared by heads
    -> RoPE2D on q and k                        optional (a ``RopeTable`` passed at call time)
    -> F.scaled_dot_product_attention           scale 1/sqrt(head_dim); V gets no norm, no RoPE
    -> proj Linear

SDPA runs with PyTorch's default kernel selection, so the fused (flash) kernels are used on CPU and
GPU, in fp32 and bf16. A boolean ``attn_mask`` follows SDPA's convention: True = may attend.

Three uses, which differ only in where K and V come from and go to:

- ``forward``: plain attention over the input sequence.
- ``forward_map``: also returns this layer's K (after k_norm and RoPE) and V, exactly as they
  enter the attention — what a KV cache stores.
- ``forward_track``: the input's own K/V are written into a cache buffer's scratch region right
  after the cached tokens, and the queries attend over ``buffer[:, :, :length + own]``. Only the
  new tokens are copied; the cache is never concatenated.
- ``forward_past``: the same attention in the form an exported graph can hold: past K/V are
  inputs, sliced to their length and concatenated with the input's own.

``CacheBuffers`` is the structural type the models layer needs from a cache (the cache package
implements it; models may not import it).
"""

from __future__ import annotations

from typing import Protocol

import torch
import torch.nn.functional as F
from torch import nn

from kvtracker_sdk.errors import CacheError, ConfigError
from kvtracker_sdk.models.layers.cached_attention import cached_attention
from kvtracker_sdk.models.layers.rope2d import RopeTable

__all__ = ["Attention", "CacheBuffers", "check_cache_buffers", "keyframe_query_mask"]


class CacheBuffers(Protocol):
    """Per-layer K/V buffers with spare capacity: what a tracking pass reads and scratches.

    ``buffers(layer)`` returns full-capacity K and V tensors [1, heads, capacity, head_dim] of the
    ``layer``-th cached layer (ordinal among the cached layers); its tokens
    ``[:layer_length(layer)]`` are cached, the tokens after them are scratch that a pass may
    overwrite. ``length`` is the longest layer's (layers differ only in a pruned cache). A cache
    that fills its buffers on demand (a quantised one dequantises a layer per call) may also offer
    ``peek_buffers(layer)``: the same tensors unfilled, which ``check_cache_buffers`` then uses.
    """

    @property
    def length(self) -> int: ...

    def layer_length(self, layer: int) -> int: ...

    def ensure_capacity(self, tokens: int) -> None: ...

    def buffers(self, layer: int) -> tuple[torch.Tensor, torch.Tensor]: ...


def check_cache_buffers(
    cache: CacheBuffers,
    *,
    block_indices: tuple[int, ...],
    num_heads: int,
    head_dim: int,
    dtype: torch.dtype,
    device: torch.device,
) -> None:
    """Raise ``CacheError`` unless every cached layer (one per global block in
    ``block_indices``) has K/V buffers [1, num_heads, tokens, head_dim] of ``dtype`` on ``device``."""
    expected = (1, num_heads, head_dim)
    peek = getattr(cache, "peek_buffers", cache.buffers)  # checking need not fill them
    for ordinal, block_index in enumerate(block_indices):
        try:
            key_buffer, value_buffer = peek(ordinal)
        except IndexError as exc:
            raise CacheError(
                f"the cache has no layer {ordinal} (block {block_index}); the model has "
                f"{len(block_indices)} global layers"
            ) from exc
        for buffer in (key_buffer, value_buffer):
            if buffer.dim() != 4 or (buffer.shape[0], buffer.shape[1], buffer.shape[3]) != expected:
                raise CacheError(
                    f"cache layer {ordinal}: buffer {tuple(buffer.shape)} does not fit "
                    f"[1, {num_heads}, tokens, {head_dim}]"
                )
            if buffer.dtype != dtype or buffer.device != device:
                raise CacheError(
                    f"cache layer {ordinal} is {buffer.dtype} on {buffer.device}, the model computes "
                    f"in {dtype} on {device}; convert it with cache.to(dtype=..., device=...)"
                )


def keyframe_query_mask(
    cached_tokens: int,
    num_queries: int,
    tokens_per_frame: int,
    *,
    queries_only: bool = False,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """bool [S, S], S = cached_tokens + num_queries * tokens_per_frame; True = may attend.

    Cached (keyframe) tokens see only cached tokens; each query frame's tokens see every cached
    token and the tokens of their own frame. A full forward on [keyframes, queries] under this
    mask equals tracking each query against the keyframes' cache. ``queries_only`` returns just
    the query rows [num_queries * tokens_per_frame, S]: the mask of a tracking pass over several
    independent queries (without building the S x S matrix).
    """
    # owner frame of each token: -1 for cached tokens, the query index otherwise
    owner = torch.cat(
        (
            torch.full((cached_tokens,), -1, device=device),
            torch.arange(num_queries, device=device).repeat_interleave(tokens_per_frame),
        )
    )
    rows = owner[cached_tokens:] if queries_only else owner
    return (owner.unsqueeze(0) < 0) | (owner.unsqueeze(0) == rows.unsqueeze(1))


class Attention(nn.Module):
    """Self-attention; parameter names match DINOv2/Pi3/DA3 (``qkv``, ``q_norm``, ``k_norm``, ``proj``)."""

    def __init__(
        self,
        dim: int,
        num_heads: int,
        *,
        qkv_bias: bool = True,
        proj_bias: bool = True,
        qk_norm: bool = False,
        qk_norm_eps: float = 1e-5,
    ) -> None:
        super().__init__()
        if dim % num_heads != 0:
            raise ConfigError(f"attention dim {dim} is not divisible by num_heads {num_heads}")
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.qkv = nn.Linear(dim, 3 * dim, bias=qkv_bias)
        self.q_norm: nn.Module = (
            nn.LayerNorm(self.head_dim, eps=qk_norm_eps) if qk_norm else nn.Identity()
        )
        self.k_norm: nn.Module = (
            nn.LayerNorm(self.head_dim, eps=qk_norm_eps) if qk_norm else nn.Identity()
        )
        self.proj = nn.Linear(dim, dim, bias=proj_bias)
        # kernel of forward_track's attention over the cache (models/layers/cached_attention.py)
        self.cached_kernel = "sdpa"

    def project(
        self, x: torch.Tensor, rope: RopeTable | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """q, k, v [B, heads, L, head_dim] of ``x`` [B, L, dim], q/k normed and rotated."""
        batch, length, dim = x.shape
        # [B, L, 3*dim] -> [3, B, heads, L, head_dim]
        qkv = (
            self.qkv(x)
            .reshape(batch, length, 3, self.num_heads, self.head_dim)
            .permute(2, 0, 3, 1, 4)
        )
        q, k, v = qkv.unbind(0)
        q, k = self.q_norm(q), self.k_norm(k)
        if q.dtype != v.dtype:  # CUDA autocast norms in fp32: K/V share a dtype (official Pi3)
            q, k = q.to(v.dtype), k.to(v.dtype)
        if rope is not None:
            q, k = rope.apply(q), rope.apply(k)
        return q, k, v

    def _merge(self, attended: torch.Tensor) -> torch.Tensor:
        # [B, heads, L, head_dim] -> [B, L, dim] -> proj
        return self.proj(attended.transpose(1, 2).flatten(2))

    def forward(
        self,
        x: torch.Tensor,
        *,
        rope: RopeTable | None = None,
        attn_mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """[B, L, dim] -> [B, L, dim]; ``attn_mask`` bool [L, L] (or broadcastable), True = attend."""
        q, k, v = self.project(x, rope)
        return self._merge(F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask))

    def forward_map(
        self,
        x: torch.Tensor,
        *,
        rope: RopeTable | None = None,
        attn_mask: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Like ``forward``, also returning K and V [B, heads, L, head_dim] as fed to SDPA."""
        q, k, v = self.project(x, rope)
        out = self._merge(F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask))
        # v is a view of the fused qkv output: copy it so a caller keeping V does not keep qkv (3x)
        return out, k, v.contiguous()

    def forward_track(
        self,
        x: torch.Tensor,
        key_buffer: torch.Tensor,
        value_buffer: torch.Tensor,
        past_length: int,
        *,
        rope: RopeTable | None = None,
        attn_mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Attend from ``x`` [1, L, dim] over cached tokens plus its own tokens.

        ``key_buffer``/``value_buffer`` [1, heads, capacity, head_dim] hold ``past_length`` cached
        tokens and must have room for ``L`` more; this call overwrites ``[past_length:
        past_length + L]`` with its own K/V (scratch) and attends over ``[:past_length + L]``.
        ``attn_mask`` bool [L, past_length + L] (None: every query sees every token). The
        attention kernel is ``self.cached_kernel`` (``models/layers/cached_attention.py``).
        """
        q, k, v = self.project(x, rope)
        end = past_length + x.shape[1]
        key_buffer[:, :, past_length:end].copy_(k)
        value_buffer[:, :, past_length:end].copy_(v)
        attended = cached_attention(
            q, key_buffer[:, :, :end], value_buffer[:, :, :end], attn_mask,
            kernel=self.cached_kernel,
        )  # fmt: skip
        return self._merge(attended)

    def forward_past(
        self,
        x: torch.Tensor,
        past_key: torch.Tensor,
        past_value: torch.Tensor,
        past_length: torch.Tensor,
        *,
        rope: RopeTable | None = None,
    ) -> torch.Tensor:
        """``forward_track`` for exported graphs: ``x`` [1, L, dim] attends over
        ``past[:, :, :past_length]`` (int64 [] tensor) plus its own K/V, read by slicing and
        concatenation since ONNX cannot write a buffer in place.

        The attention is spelled out (softmax(q kᵀ / sqrt(d)) v) rather than
        ``F.scaled_dot_product_attention``: ONNX Runtime then folds the key transpose into its
        MatMul, faster than the exporter's decomposition of SDPA
        (``benchmarks/README.md#figures-behind-the-code``).
        """
        q, k, v = self.project(x, rope)  # [1, heads, L, head_dim] each
        keys = torch.cat((past_key[:, :, :past_length], k), dim=2)  # [1, heads, past + L, d]
        values = torch.cat((past_value[:, :, :past_length], v), dim=2)
        scores = torch.matmul(q * q.shape[-1] ** -0.5, keys.transpose(-1, -2))  # [1, h, L, past + L]
        return self._merge(torch.matmul(torch.softmax(scores, dim=-1), values))

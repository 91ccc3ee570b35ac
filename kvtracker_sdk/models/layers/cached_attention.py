"""The attention of a tracking step over the cache: which kernel computes softmax(q kᵀ/√d) v.

``Attention.forward_track`` hands its queries [1, heads, L, d] and the cache's K/V [1, heads, S, d]
(S = cached + own tokens) to ``cached_attention`` with the layer's ``cached_kernel``:

- ``"sdpa"`` (default): ``F.scaled_dot_product_attention``, PyTorch's fused CPU flash kernel. Its
  scores are fp32. On CPUs without AMX its bf16 products run at about the fp32 matrix-product
  rate, far below a bf16 GEMM's (``benchmarks/attention_kernels.py``; figures:
  ``benchmarks/README.md#figures-behind-the-code``).
- ``"products"``: two batched matrix products at the full bf16 GEMM rate, 64 queries at a time
  (the scores of a chunk stay in cache): scores in the operands' dtype, softmax accumulated in
  fp32 (max-subtracted, so it cannot overflow), probabilities in the operands' dtype for P·V.
  In bf16 the scores are rounded to bf16 before the softmax, which the flash kernel does not do:
  the attention output deviates more from float64; the runtimes benchmark measures what that
  does to poses. Faster than ``"sdpa"`` for DA3-Small's 6 heads on short caches; slower for long
  caches, where the scores of a chunk no longer fit the caches (figures: the same section).

``use_cached_kernel(model, name)`` sets it on every attention layer of a model.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from kvtracker_sdk.errors import ConfigError

__all__ = ["CACHED_KERNELS", "cached_attention", "use_cached_kernel"]

CACHED_KERNELS = ("sdpa", "products")
_QUERY_CHUNK = 64  # queries per pair of products: a chunk's scores [heads, 64, S] stay small


def cached_attention(
    q: torch.Tensor,
    keys: torch.Tensor,
    values: torch.Tensor,
    attn_mask: torch.Tensor | None = None,
    *,
    kernel: str = "sdpa",
) -> torch.Tensor:
    """softmax(q kᵀ / √d) v: ``q`` [B, heads, L, d], ``keys``/``values`` [B, heads, S, d],
    ``attn_mask`` bool [L, S] or [1, S] (True = may attend; every row must allow a key)
    -> [B, heads, L, d]."""
    if kernel == "sdpa":
        return F.scaled_dot_product_attention(q, keys, values, attn_mask=attn_mask)
    if kernel != "products":
        raise ConfigError(f"unknown cached attention kernel {kernel!r}; one of {CACHED_KERNELS}")
    out = torch.empty_like(q)
    keys_t = keys.transpose(-1, -2)  # [B, heads, d, S]: the product reads it without a copy
    scale = q.shape[-1] ** -0.5  # 1/8 for d = 64: exact in bf16
    for start in range(0, q.shape[-2], _QUERY_CHUNK):
        stop = start + _QUERY_CHUNK
        scores = torch.matmul(q[..., start:stop, :] * scale, keys_t)  # [B, heads, chunk, S]
        if attn_mask is not None:  # [L, S], or [1, S] for every query alike
            rows = attn_mask if attn_mask.shape[0] == 1 else attn_mask[start:stop]
            scores = scores.masked_fill(~rows, float("-inf"))
        weights = torch.softmax(scores, dim=-1, dtype=torch.float32).to(values.dtype)
        out[..., start:stop, :] = torch.matmul(weights, values)
    return out


def use_cached_kernel(model: nn.Module, kernel: str) -> nn.Module:
    """Set ``kernel`` (one of ``CACHED_KERNELS``) on every attention layer of ``model``."""
    if kernel not in CACHED_KERNELS:
        raise ConfigError(f"unknown cached attention kernel {kernel!r}; one of {CACHED_KERNELS}")
    for module in model.modules():
        if isinstance(getattr(module, "cached_kernel", None), str):
            module.__dict__["cached_kernel"] = kernel  # a plain attribute of ``Attention``
    return model

"""SwiGLU feed-forward network (DINOv2's ``SwiGLUFFNFused``, used by ViT-g/14 backbones).

``w3(silu(a) * b)`` with ``[a | b] = w12(x)``. The hidden width follows DINOv2's rule for the
nominal width ``n = dim * mlp_ratio``: ``h = ceil8(int(n * 2 / 3))``, which keeps the parameter
count of a GELU MLP of width ``n`` (ViT-g: dim 1536, n 6144 -> h 4096). Checkpoint names ``w12`` /
``w3`` are those of DINOv2 with or without xformers.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["SwiGLUFFN", "swiglu_hidden_dim"]


def swiglu_hidden_dim(nominal_hidden_dim: int) -> int:
    """DINOv2's SwiGLU width for a nominal MLP width: 2/3 of it, rounded up to a multiple of 8."""
    return (int(nominal_hidden_dim * 2 / 3) + 7) // 8 * 8


class SwiGLUFFN(nn.Module):
    """[..., dim] -> [..., out_dim]; ``hidden_dim`` is the nominal width (rounded as above)."""

    def __init__(
        self, dim: int, hidden_dim: int, out_dim: int | None = None, *, bias: bool = True
    ) -> None:
        super().__init__()
        hidden = swiglu_hidden_dim(hidden_dim)
        self.w12 = nn.Linear(dim, 2 * hidden, bias=bias)
        self.w3 = nn.Linear(hidden, out_dim or dim, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        gate, value = self.w12(x).chunk(2, dim=-1)
        return self.w3(F.silu(gate) * value)

"""The transformer feed-forward network: Linear -> GELU -> Linear (``fc1``, ``fc2`` as in DINOv2)."""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["Mlp"]


class Mlp(nn.Module):
    """[..., dim] -> [..., out_dim]; exact (erf) GELU, as the DINOv2/Pi3/DA3 checkpoints expect."""

    def __init__(
        self, dim: int, hidden_dim: int, out_dim: int | None = None, *, bias: bool = True
    ) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden_dim, bias=bias)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden_dim, out_dim or dim, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))

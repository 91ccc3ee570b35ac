"""LayerScale (CaiT, used by DINOv2): a learned per-channel scale on each residual branch."""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["LayerScale"]


class LayerScale(nn.Module):
    """``x * gamma`` with ``gamma`` [dim] (checkpoint name ``ls1.gamma`` / ``ls2.gamma``)."""

    def __init__(self, dim: int, init_value: float = 1e-5) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), float(init_value)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma

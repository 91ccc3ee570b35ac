"""Building blocks of DA3's DPT head: refinement units, top-down fusion, UV position embedding.

These follow the DPT design (Ranftl et al., "Vision Transformers for Dense Prediction") as DA3
configures it: no batch norm, ReLU activations, bilinear upsampling with ``align_corners=True``.
Module names match the checkpoint (``resConfUnit1/2.conv1/2``, ``out_conv``).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["ChannelsLast", "FusionBlock", "ResidualConvUnit", "add_uv_embedding", "uv_embedding"]


class ResidualConvUnit(nn.Module):
    """``x + conv2(relu(conv1(relu(x))))`` with 3x3 convolutions, [B, C, h, w] -> same."""

    def __init__(self, features: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, padding=1)
        self.conv2 = nn.Conv2d(features, features, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class FusionBlock(nn.Module):
    """One top-down fusion step: ``out_conv(upsample(rcu2(top + rcu1(lateral))))``.

    The coarsest level has no lateral input (``has_residual=False``: no ``resConfUnit1``). The
    result is resized to ``size`` when given, else upsampled x2 (size ``int(2 * h)``).
    """

    def __init__(self, features: int, *, has_residual: bool = True) -> None:
        super().__init__()
        self.resConfUnit1 = ResidualConvUnit(features) if has_residual else None
        self.resConfUnit2 = ResidualConvUnit(features)
        self.out_conv = nn.Conv2d(features, features, 1)

    def forward(
        self,
        top: torch.Tensor,
        lateral: torch.Tensor | None = None,
        *,
        size: tuple[int, int] | None = None,
    ) -> torch.Tensor:
        if self.resConfUnit1 is not None and lateral is not None:
            top = top + self.resConfUnit1(lateral)
        top = self.resConfUnit2(top)
        size = size or (2 * top.shape[-2], 2 * top.shape[-1])
        return self.out_conv(F.interpolate(top, size=size, mode="bilinear", align_corners=True))


class ChannelsLast(nn.Module):
    """Apply a channel-wise module (LayerNorm) to [B, C, h, w] by moving C last and back.

    The official head expresses this as ``Permute``, ``LayerNorm``, ``Permute`` inside an
    ``nn.Sequential``; this wrapper is used in the same slots so the LayerNorm keeps its index.
    """

    def __init__(self, to_last: bool) -> None:
        super().__init__()
        self.to_last = to_last

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.permute(0, 2, 3, 1) if self.to_last else x.permute(0, 3, 1, 2)


def _sincos(positions: torch.Tensor, width: int, omega_0: float) -> torch.Tensor:
    """[M] positions -> [M, width]: sin then cos of positions * omega_0^(-2j/width), j < width/2."""
    omega = torch.arange(width // 2, dtype=torch.float32, device=positions.device) / (width / 2.0)
    angles = positions.reshape(-1, 1).float() * (1.0 / omega_0**omega)
    return torch.cat((angles.sin(), angles.cos()), dim=1)


def uv_embedding(
    height: int,
    width: int,
    channels: int,
    *,
    aspect_ratio: float,
    dtype: torch.dtype,
    device: torch.device,
    omega_0: float = 100.0,
) -> torch.Tensor:
    """Sinusoidal embedding [channels, height, width] of normalised UV coordinates.

    u spans ``±a/sqrt(a²+1) * (width-1)/width`` and v ``±1/sqrt(a²+1) * (height-1)/height`` with
    ``a = aspect_ratio`` (the image's W/H, whatever the map's own size), so the embedding marks
    the same image location at every pyramid level. Channels: [sin u, cos u, sin v, cos v], each
    ``channels / 4`` wide. The grid is built in ``dtype`` (as the reference does), the sinusoids
    in fp32.
    """
    diagonal = math.sqrt(aspect_ratio**2 + 1.0)
    span_u = aspect_ratio / diagonal * (width - 1) / width
    span_v = 1.0 / diagonal * (height - 1) / height
    u = torch.linspace(-span_u, span_u, width, dtype=dtype, device=device)
    v = torch.linspace(-span_v, span_v, height, dtype=dtype, device=device)
    grid_v, grid_u = torch.meshgrid(v, u, indexing="ij")  # [height, width] each
    embedding = torch.cat(
        (_sincos(grid_u, channels // 2, omega_0), _sincos(grid_v, channels // 2, omega_0)), dim=1
    )  # [height * width, channels]
    return embedding.reshape(height, width, channels).permute(2, 0, 1)


def add_uv_embedding(
    x: torch.Tensor, image_size: tuple[int, int], ratio: float = 0.1
) -> torch.Tensor:
    """``x + ratio * uv_embedding`` for a feature map [B, C, h, w] of an image (H, W)."""
    height, width = image_size
    embedding = uv_embedding(
        x.shape[-2],
        x.shape[-1],
        x.shape[1],
        aspect_ratio=width / height,
        dtype=x.dtype,
        device=x.device,
    )
    return x + embedding * ratio

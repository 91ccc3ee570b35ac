"""Building blocks of DA3's DPT head: refinement units, top-down fusion, UV position embedding.

These follow the DPT design (Ranftl et al., "Vision Transformers for Dense Prediction") as DA3
configures it: no batch norm, ReLU activations, bilinear upsampling with ``align_corners=True``.
Module names match the checkpoint (``resConfUnit1/2.conv1/2``, ``out_conv``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from kvtracker_sdk.models.layers.symbolic_sizes import size_tensor

__all__ = [
    "ChannelsLast",
    "FusionBlock",
    "PointwiseConv",
    "ResidualConvUnit",
    "add_uv_embedding",
    "uv_embedding",
]


class PointwiseConv(nn.Conv2d):
    """A 1x1 ``nn.Conv2d`` (same parameters and names) that keeps a channels-last input's layout.

    On a channels-last [B, C, h, w] input on the CPU (eager) it is the matrix product of the
    [B, h, w, C] pixels with the [out, C] weight, whose result is channels-last again. PyTorch's
    CPU convolution instead sends a single-threaded 1x1 convolution to its reference kernel,
    which returns NCHW: the next 3x3 convolution (oneDNN, channels-last) would reorder it, then
    this one again. Elsewhere (GPU, traced or exported) it is the ordinary convolution.
    """

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__(in_channels, out_channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        eager_cpu = x.device.type == "cpu" and not torch.compiler.is_compiling()
        if not eager_cpu or not x.is_contiguous(memory_format=torch.channels_last):
            return super().forward(x)
        pixels = F.linear(x.permute(0, 2, 3, 1), self.weight.flatten(1), self.bias)
        return pixels.permute(0, 3, 1, 2)


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
        self.out_conv = PointwiseConv(features, features)

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


def _symmetric_range(half_span: torch.Tensor, count: int, device: torch.device) -> torch.Tensor:
    """``linspace(-half_span, half_span, count)`` in float64 (``count`` may be symbolic: see
    ``models/layers/symbolic_sizes.py``)."""
    step = 2 * half_span / torch.clamp(size_tensor(count, device) - 1, min=1)
    return torch.arange(count, dtype=torch.float64, device=device) * step - half_span


def uv_embedding(
    height: int,
    width: int,
    channels: int,
    *,
    image_size: tuple[int, int],
    dtype: torch.dtype,
    device: torch.device,
    omega_0: float = 100.0,
) -> torch.Tensor:
    """Sinusoidal embedding [channels, height, width] of normalised UV coordinates.

    u spans ``±a/sqrt(a²+1) * (width-1)/width`` and v ``±1/sqrt(a²+1) * (height-1)/height`` with
    ``a`` the image's W/H (``image_size`` = (H, W), whatever the map's own size), so the
    embedding marks the same image location at every pyramid level. Channels: [sin u, cos u,
    sin v, cos v], each ``channels / 4`` wide. The grid is computed in float64 and rounded to
    ``dtype`` (the reference builds it with ``linspace`` in ``dtype``: equal to ~1 ulp), the
    sinusoids in fp32.
    """
    image_h, image_w = (size_tensor(side, device) for side in image_size)
    map_h, map_w = size_tensor(height, device), size_tensor(width, device)
    aspect = image_w / image_h
    diagonal = torch.sqrt(aspect * aspect + 1.0)
    span_u = aspect / diagonal * (map_w - 1) / map_w
    span_v = 1.0 / diagonal * (map_h - 1) / map_h
    u = _symmetric_range(span_u, width, device).to(dtype)
    v = _symmetric_range(span_v, height, device).to(dtype)
    grid_v, grid_u = torch.meshgrid(v, u, indexing="ij")  # [height, width] each
    embedding = torch.cat(
        (_sincos(grid_u, channels // 2, omega_0), _sincos(grid_v, channels // 2, omega_0)), dim=1
    )  # [height * width, channels]
    return embedding.reshape(height, width, channels).permute(2, 0, 1)


def _scaled_uv_embedding(
    x: torch.Tensor, image_size: tuple[int, int], ratio: float
) -> torch.Tensor:
    """``ratio * uv_embedding`` [C, h, w] for ``x`` [B, C, h, w]: computed, not remembered."""
    embedding = uv_embedding(
        x.shape[-2],
        x.shape[-1],
        x.shape[1],
        image_size=image_size,
        dtype=x.dtype,
        device=x.device,
    )
    return embedding * ratio


# (h, w, C, image size, ratio, dtype, device) -> ratio * uv_embedding; a tracker sees a handful
_UV_MEMO: dict[tuple[object, ...], torch.Tensor] = {}
_UV_MEMO_SIZE = 32


def add_uv_embedding(
    x: torch.Tensor, image_size: tuple[int, int], ratio: float = 0.1
) -> torch.Tensor:
    """``x + ratio * uv_embedding`` for a feature map [B, C, h, w] of an image (H, W).

    The embedding depends only on the sizes, so eager CPU calls reuse it: computing it costs as
    much as a convolution of the head at full resolution (sines and cosines of every pixel).
    Traced and exported calls compute it, so that the graph keeps its symbolic sizes, and so do
    GPU calls (a tensor made while a CUDA graph captures lives in that graph's memory pool).
    """
    sizes = (*x.shape[1:], *image_size)
    eager_cpu = x.device.type == "cpu" and not torch.compiler.is_compiling()
    if not eager_cpu or not all(isinstance(n, int) for n in sizes):
        return x + _scaled_uv_embedding(x, image_size, ratio)
    key = (*sizes, ratio, x.dtype, x.device)
    embedding = _UV_MEMO.get(key)
    if embedding is None:
        if len(_UV_MEMO) >= _UV_MEMO_SIZE:
            _UV_MEMO.clear()
        embedding = _UV_MEMO[key] = _scaled_uv_embedding(x, image_size, ratio)
    return x + embedding

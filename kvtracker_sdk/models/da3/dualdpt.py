"""DA3's DualDPT head: per-view depth and confidence, plus the auxiliary ray branch.

Per view (nothing here mixes views), from the four feature maps [h*w, 2C] of the backbone::

    LayerNorm -> [2C, h, w] -> 1x1 conv to out_channels[i] -> + 0.1 UV embedding
    -> resize to a pyramid: x4 (transposed conv), x2 (transposed conv), x1, /2 (strided conv)
    -> 3x3 conv to ``features`` (``scratch.layer{i}_rn``)
    -> top-down fusion (``refinenet4`` ... ``refinenet1``): the finest map is (8h, 8w)

- main branch: ``output_conv1`` (3x3, features/2), bilinear resize to the image (14h, 14w),
  + UV embedding, ``output_conv2`` (3x3 to 32, ReLU, 1x1 to 2): depth = exp(c0),
  confidence = exp(c1) + 1 (so >= 1).
- auxiliary branch (its own fusion chain ``refinenet*_aux``): at (8h, 8w), ``output_conv1_aux[3]``
  (five 3x3 convs, no activation), + UV embedding, ``output_conv2_aux[3]`` (3x3 to 32,
  channel LayerNorm, ReLU, 1x1 to 7): ray = c0..5 (linear), ray confidence = exp(c6) + 1.

The aux branch is trained at four pyramid levels; inference reads only the last, so levels 0-2
of ``output_conv1_aux`` / ``output_conv2_aux`` are held only so that official checkpoints load
strictly. Their LayerNorm (index 2) is **one module shared by the four levels**, as in the
official code, so the checkpoint's four copies stay tied. DA3 drops the rays when it has a camera
decoder; they are computed here only on request (``with_rays``).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import torch
import torch.nn.functional as F
from torch import nn

from kvtracker_sdk.models.da3.config import DA3HeadConfig
from kvtracker_sdk.models.da3.dpt_blocks import (
    ChannelsLast,
    FusionBlock,
    PointwiseConv,
    add_uv_embedding,
)

__all__ = ["DualDPT", "DualDPTOutput"]

_HIDDEN = 32  # width before the final 1x1 convolutions (fixed in DA3)
_AUX_LEVELS = 4


@dataclass(frozen=True)
class DualDPTOutput:
    """Per-view maps (float32); the rays are None unless requested."""

    depth: torch.Tensor  # [V, H, W] > 0, along the camera z axis, up to scale
    depth_conf: torch.Tensor  # [V, H, W] >= 1
    ray: torch.Tensor | None = None  # [V, 8h, 8w, 6] raw aux output, fused-feature resolution
    ray_conf: torch.Tensor | None = None  # [V, 8h, 8w] >= 1


class _Scratch(nn.Module):
    """``head.scratch``: lateral convs, the two fusion chains and the output convolutions."""

    def __init__(self, features: int, channels: tuple[int, int, int, int]) -> None:
        super().__init__()
        self.layer1_rn, self.layer2_rn, self.layer3_rn, self.layer4_rn = (
            nn.Conv2d(width, features, 3, padding=1, bias=False) for width in channels
        )
        self.refinenet1, self.refinenet2, self.refinenet3 = (
            FusionBlock(features) for _ in range(3)
        )
        self.refinenet4 = FusionBlock(features, has_residual=False)
        self.output_conv1 = nn.Conv2d(features, features // 2, 3, padding=1)
        self.output_conv2 = nn.Sequential(
            nn.Conv2d(features // 2, _HIDDEN, 3, padding=1), nn.ReLU(), PointwiseConv(_HIDDEN, 2)
        )
        self.refinenet1_aux, self.refinenet2_aux, self.refinenet3_aux = (
            FusionBlock(features) for _ in range(3)
        )
        self.refinenet4_aux = FusionBlock(features, has_residual=False)
        self.output_conv1_aux = nn.ModuleList(_aux_neck(features) for _ in range(_AUX_LEVELS))
        shared_norm = nn.LayerNorm(_HIDDEN)
        self.output_conv2_aux = nn.ModuleList(
            nn.Sequential(
                nn.Conv2d(features // 2, _HIDDEN, 3, padding=1),
                ChannelsLast(to_last=True),
                shared_norm,
                ChannelsLast(to_last=False),
                nn.ReLU(),
                nn.Conv2d(_HIDDEN, 7, 1),
            )
            for _ in range(_AUX_LEVELS)
        )

    def lateral(self, pyramid: list[torch.Tensor]) -> list[torch.Tensor]:
        """The four resized maps (fine to coarse) -> ``features`` channels each."""
        convs = (self.layer1_rn, self.layer2_rn, self.layer3_rn, self.layer4_rn)
        return [conv(x) for conv, x in zip(convs, pyramid, strict=True)]

    def fuse(self, lateral: list[torch.Tensor], *, aux: bool) -> torch.Tensor:
        """Top-down fusion of the lateral maps (main or aux chain) -> the finest map (8h, 8w)."""
        chain = (
            (self.refinenet4_aux, self.refinenet3_aux, self.refinenet2_aux, self.refinenet1_aux)
            if aux
            else (self.refinenet4, self.refinenet3, self.refinenet2, self.refinenet1)
        )
        out = chain[0](lateral[3], size=lateral[2].shape[-2:])
        out = chain[1](out, lateral[2], size=lateral[1].shape[-2:])
        out = chain[2](out, lateral[1], size=lateral[0].shape[-2:])
        return chain[3](out, lateral[0])


def _aux_neck(features: int) -> nn.Sequential:
    """``output_conv1_aux[i]``: five 3x3 convs alternating features/2 and features, no activation."""
    half = features // 2
    widths = (features, half, features, half, features, half)
    return nn.Sequential(*(nn.Conv2d(a, b, 3, padding=1) for a, b in pairwise(widths)))


def _channels_last(x: torch.Tensor) -> torch.Tensor:
    """``x`` [B, C, h, w] stored channels-last, the layout oneDNN's CPU convolutions compute in:
    every convolution, addition and resize after it then keeps that layout, instead of reordering
    its input and output on each call (the values are the same to float rounding)."""
    if x.device.type != "cpu" or torch.compiler.is_compiling():  # exports keep their graph
        return x
    return x.contiguous(memory_format=torch.channels_last)


class DualDPT(nn.Module):
    """``head``: features 4 x [V, h*w, dim_in] -> ``DualDPTOutput`` (V views, any batching)."""

    def __init__(self, dim_in: int, config: DA3HeadConfig, *, patch_size: int = 14) -> None:
        super().__init__()
        self.patch_size = patch_size
        features, channels = config.features, config.out_channels
        self.norm = nn.LayerNorm(dim_in)
        self.projects = nn.ModuleList(PointwiseConv(dim_in, width) for width in channels)
        self.resize_layers = nn.ModuleList(
            [
                nn.ConvTranspose2d(channels[0], channels[0], kernel_size=4, stride=4),
                nn.ConvTranspose2d(channels[1], channels[1], kernel_size=2, stride=2),
                nn.Identity(),
                nn.Conv2d(channels[3], channels[3], kernel_size=3, stride=2, padding=1),
            ]
        )
        self.scratch = _Scratch(features, channels)

    def forward(
        self,
        features: list[torch.Tensor],
        image_size: tuple[int, int],
        *,
        with_rays: bool = False,
        views_per_chunk: int = 8,
    ) -> DualDPTOutput:
        """Features 4 x [V, h*w, dim_in] of images (H, W) -> per-view maps.

        Views are processed ``views_per_chunk`` at a time to bound the memory of the
        full-resolution maps; each view's result does not depend on the chunking.
        """
        chunks = [
            self.forward_views(
                [f[start : start + views_per_chunk] for f in features], image_size, with_rays
            )
            for start in range(0, features[0].shape[0], views_per_chunk)
        ]
        if len(chunks) == 1:
            return chunks[0]

        def joined(name: str) -> torch.Tensor | None:
            parts = [getattr(chunk, name) for chunk in chunks]
            return None if parts[0] is None else torch.cat(parts)

        return DualDPTOutput(
            depth=torch.cat([chunk.depth for chunk in chunks]),
            depth_conf=torch.cat([chunk.depth_conf for chunk in chunks]),
            ray=joined("ray"),
            ray_conf=joined("ray_conf"),
        )

    def forward_views(
        self, features: list[torch.Tensor], image_size: tuple[int, int], with_rays: bool
    ) -> DualDPTOutput:
        """``forward`` on all the views at once (no chunking; the exported depth graph runs this)."""
        height, width = image_size
        grid_h, grid_w = height // self.patch_size, width // self.patch_size
        pyramid = []
        for level, tokens in enumerate(features):
            # [V, h*w, dim_in] -> [V, dim_in, h, w]
            x = self.norm(tokens).transpose(1, 2).reshape(tokens.shape[0], -1, grid_h, grid_w)
            x = add_uv_embedding(self.projects[level](_channels_last(x)), image_size)
            pyramid.append(self.resize_layers[level](x))
        s = self.scratch
        lateral = s.lateral(pyramid)

        main = s.output_conv1(s.fuse(lateral, aux=False))  # [V, features/2, 8h, 8w]
        size = (grid_h * self.patch_size, grid_w * self.patch_size)
        main = F.interpolate(main, size=size, mode="bilinear", align_corners=True)
        logits = s.output_conv2(add_uv_embedding(main, image_size))  # [V, 2, H, W]
        depth, depth_conf = torch.exp(logits[:, 0]), torch.exp(logits[:, 1]) + 1.0
        if not with_rays:
            return DualDPTOutput(depth=depth, depth_conf=depth_conf)

        aux = s.output_conv1_aux[-1](s.fuse(lateral, aux=True))
        aux_logits = s.output_conv2_aux[-1](add_uv_embedding(aux, image_size)).permute(0, 2, 3, 1)
        ray_conf = torch.exp(aux_logits[..., 6]) + 1.0
        return DualDPTOutput(
            depth=depth, depth_conf=depth_conf, ray=aux_logits[..., :6], ray_conf=ray_conf
        )

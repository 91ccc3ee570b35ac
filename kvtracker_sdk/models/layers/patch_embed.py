"""Patch embedding: a stride-``p`` ``p``x``p`` convolution, flattened to a row-major token sequence."""

from __future__ import annotations

import torch
from torch import nn

from kvtracker_sdk.errors import ImageShapeError

__all__ = ["IMAGENET_MEAN", "IMAGENET_STD", "PatchEmbed"]

# RGB statistics every family's DINOv2 encoder was trained with (its inputs are normalised by them)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class PatchEmbed(nn.Module):
    """[B, C, H, W] -> [B, (H/p)*(W/p), dim] (checkpoint name ``patch_embed.proj``)."""

    def __init__(self, patch_size: int, embed_dim: int, in_channels: int = 3) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Conv2d(in_channels, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        height, width = images.shape[-2:]
        if height % self.patch_size or width % self.patch_size:
            raise ImageShapeError(
                f"image size {height}x{width} is not a multiple of the patch size {self.patch_size}"
            )
        # [B, dim, h, w] -> [B, h*w, dim], row-major over the patch grid
        return self.proj(images).flatten(2).transpose(1, 2)

"""Small random DA3 models for tests (no checkpoint needed).

``randomise_`` follows the golden generator's scheme (``../shared/golden/da3/README.md``) so that
every parameter matters and outputs stay O(1): LayerScale 0.5 + 0.1N, LayerNorm weights 1 + 0.1N,
biases 0.05N, tokens 0.5N, weights N/sqrt(fan_in), the final depth conv x0.3 and a positive
field-of-view bias. PyTorch's default init would leave the camera tokens and global attention
with too small an effect to test.
"""

from __future__ import annotations

import math

import torch

from kvtracker_sdk.models.da3 import (
    DA3BackboneConfig,
    DA3CameraEncoderConfig,
    DA3Config,
    DA3HeadConfig,
    DepthAnything3,
)

_TOKENS = ("cls_token", "camera_token", "pos_embed")


def tiny_config(
    *,
    dim: int = 16,
    heads: int = 2,
    depth: int = 6,
    alt_start: int = 2,
    out_layers: tuple[int, int, int, int] = (2, 3, 4, 5),
    pos_embed_grid: int = 4,
) -> DA3Config:
    """A small DA3: backbone ``dim`` wide (head_dim ``dim / heads``), 8-feature DPT head."""
    return DA3Config(
        backbone=DA3BackboneConfig(
            embed_dim=dim,
            depth=depth,
            num_heads=heads,
            alt_start=alt_start,
            out_layers=out_layers,
            pos_embed_grid=pos_embed_grid,
        ),
        head=DA3HeadConfig(features=8, out_channels=(4, 4, 8, 8)),
        cam_enc=DA3CameraEncoderConfig(depth=1, num_heads=heads),
    )


@torch.no_grad()
def randomise_(model: DepthAnything3, seed: int) -> DepthAnything3:
    """Re-draw every parameter in place (golden scheme); returns the model in eval mode."""
    generator = torch.Generator().manual_seed(seed)
    for name, param in model.named_parameters():
        noise = torch.randn(param.shape, generator=generator)
        leaf = name.rsplit(".", 1)[-1]
        if leaf in _TOKENS:
            value = 0.5 * noise
        elif leaf == "gamma":
            value = 0.5 + 0.1 * noise
        elif name == "cam_dec.fc_fov.0.bias":
            value = 1.0 + 0.05 * noise
        elif leaf == "bias":
            value = 0.05 * noise
        elif param.dim() == 1:  # LayerNorm weight
            value = 1.0 + 0.1 * noise
        else:
            value = noise / math.sqrt(math.prod(param.shape[1:]))
            if name == "head.scratch.output_conv2.2.weight":
                value = 0.3 * value
        param.copy_(value)
    return model.eval()


def random_da3(config: DA3Config | None = None, *, seed: int = 0) -> DepthAnything3:
    """A DA3 of ``config`` (default ``tiny_config()``) with golden-scheme random weights."""
    torch.manual_seed(seed)
    return randomise_(DepthAnything3(config or tiny_config()), seed)

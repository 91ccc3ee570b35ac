"""Small random Pi3 models for tests (no checkpoint needed).

``randomise_`` follows the golden generator's scheme (``../shared/golden/pi3/config.json``) so that
every parameter matters and outputs are O(1)-O(10): with PyTorch's default init the LayerScale
gammas (0.01) make the global attention's effect too small to test.
"""

from __future__ import annotations

import math

import torch

from kvtracker_sdk.models.pi3 import (
    Pi3,
    Pi3Config,
    Pi3DecoderConfig,
    Pi3EncoderConfig,
    Pi3HeadsConfig,
)

_TOKENS = ("cls_token", "register_tokens", "pos_embed", "register_token")


def tiny_config(
    *,
    dim: int = 32,
    heads: int = 2,
    depth: int = 4,
    head_dim_heads: int = 16,
    pos_embed_grid: int = 6,
) -> Pi3Config:
    """A small Pi3: encoder/decoder ``dim``, head decoders ``head_dim_heads`` wide."""
    return Pi3Config(
        encoder=Pi3EncoderConfig(
            embed_dim=dim, depth=1, num_heads=heads, pos_embed_grid=pos_embed_grid
        ),
        decoder=Pi3DecoderConfig(embed_dim=dim, depth=depth, num_heads=heads),
        heads=Pi3HeadsConfig(
            embed_dim=head_dim_heads, depth=1, num_heads=heads, point_out_dim=16, camera_out_dim=16
        ),
    )


@torch.no_grad()
def randomise_(model: torch.nn.Module, seed: int) -> torch.nn.Module:
    """Re-draw every parameter in place (golden scheme); returns the model in eval mode."""
    generator = torch.Generator().manual_seed(seed)
    for name, param in model.named_parameters():
        noise = torch.randn(param.shape, generator=generator)
        leaf = name.rsplit(".", 1)[-1]
        if leaf in _TOKENS:
            value = 0.5 * noise
        elif leaf == "gamma":
            value = 0.5 + 0.1 * noise
        elif leaf == "bias":
            value = 0.05 * noise
        elif param.dim() == 1:  # LayerNorm weight
            value = 1.0 + 0.1 * noise
        else:
            value = noise / math.sqrt(math.prod(param.shape[1:]))
        param.copy_(value)
    return model.eval()


def random_pi3(config: Pi3Config | None = None, *, seed: int = 0) -> Pi3:
    """A Pi3 of ``config`` (default ``tiny_config()``) with golden-scheme random weights."""
    torch.manual_seed(seed)
    model = Pi3(config or tiny_config())
    randomise_(model, seed)
    return model

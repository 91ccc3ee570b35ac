"""The DPT head's eager CPU fast path (channels-last, the UV embedding reused) computes what the
official form computes (NCHW convolutions, the embedding made on every call).

Both forms run the same fp32 weights on the same seeded features; they differ only in the order
of float additions inside the convolutions, so the maps agree to ~1e-6 relative (tolerance 1e-5).
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from kvtracker_sdk.models.da3 import dpt_blocks, dualdpt
from kvtracker_sdk.models.da3.dpt_blocks import PointwiseConv, add_uv_embedding
from tests.models.da3.factories import random_da3, tiny_config


def _official_add_uv_embedding(
    x: torch.Tensor, image_size: tuple[int, int], ratio: float = 0.1
) -> torch.Tensor:
    return x + dpt_blocks._scaled_uv_embedding(x, image_size, ratio)


@torch.no_grad()
def test_channels_last_head_equals_the_official_layout(monkeypatch: pytest.MonkeyPatch) -> None:
    model = random_da3(tiny_config(), seed=3)
    generator = torch.Generator().manual_seed(0)
    grid = (3, 4)  # patches: an image of 42 x 56
    width = model.head.norm.normalized_shape[0]
    features = [torch.randn(2, grid[0] * grid[1], width, generator=generator) for _ in range(4)]
    image = (grid[0] * 14, grid[1] * 14)
    fast = model.head(features, image, with_rays=True)
    monkeypatch.setattr(PointwiseConv, "forward", nn.Conv2d.forward)
    monkeypatch.setattr(dualdpt, "_channels_last", lambda x: x)
    monkeypatch.setattr(dualdpt, "add_uv_embedding", _official_add_uv_embedding)
    official = model.head(features, image, with_rays=True)
    for name in ("depth", "depth_conf", "ray", "ray_conf"):
        torch.testing.assert_close(
            getattr(fast, name), getattr(official, name), rtol=1e-5, atol=1e-6, msg=name
        )


def test_pointwise_conv_keeps_channels_last_and_the_convolution() -> None:
    torch.manual_seed(0)
    conv = PointwiseConv(6, 5)
    x = torch.randn(2, 6, 7, 9).contiguous(memory_format=torch.channels_last)
    out = conv(x)
    assert out.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(out, F.conv2d(x.contiguous(), conv.weight, conv.bias))
    assert conv(x.contiguous()).is_contiguous()  # NCHW in: the ordinary convolution


def test_reused_uv_embedding_is_the_computed_one() -> None:
    x = torch.randn(1, 8, 5, 6)
    first = add_uv_embedding(x, (70, 84))
    torch.testing.assert_close(first, _official_add_uv_embedding(x, (70, 84)), rtol=0, atol=0)
    torch.testing.assert_close(add_uv_embedding(x, (70, 84)), first, rtol=0, atol=0)
    other = add_uv_embedding(x, (70, 98))  # another image size: another embedding
    assert not torch.equal(other, first)

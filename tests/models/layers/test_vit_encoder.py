"""DinoViT: token layout, pos-embed interpolation options and checkpoint names."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from kvtracker_sdk.errors import ImageShapeError
from kvtracker_sdk.models.layers.vit_encoder import DinoViT


def _vit(**options: object) -> DinoViT:
    torch.manual_seed(0)
    defaults: dict[str, object] = {"embed_dim": 32, "depth": 2, "num_heads": 2, "pos_embed_grid": 6}
    defaults.update(options)
    return DinoViT(**defaults)  # type: ignore[arg-type]


def test_token_layout_with_registers() -> None:
    vit = _vit(num_register_tokens=4, interpolate_antialias=True)
    images = torch.rand(3, 3, 28, 42)
    tokens = vit.prepare_tokens(images)
    assert tokens.shape == (3, 1 + 4 + 6, 32)
    # registers carry no position embedding; cls does
    torch.testing.assert_close(
        tokens[:, 1:5], vit.register_tokens.expand(3, -1, -1), atol=0, rtol=0
    )
    torch.testing.assert_close(
        tokens[:, 0], (vit.cls_token + vit.pos_embed[:, :1])[:, 0].expand(3, -1)
    )
    assert vit(images).shape == (3, 6, 32)
    assert vit.num_prefix_tokens == 5


def test_interpolation_options() -> None:
    vit = _vit(interpolate_antialias=True)
    assert vit.interpolate_pos_embed(6, 6) is vit.pos_embed  # native grid: no resize
    table = vit.interpolate_pos_embed(3, 5)
    grid = vit.pos_embed[:, 1:].reshape(1, 6, 6, 32).permute(0, 3, 1, 2)
    expected = F.interpolate(grid, size=(3, 5), mode="bicubic", antialias=True)
    torch.testing.assert_close(table[:, 1:], expected.permute(0, 2, 3, 1).reshape(1, 15, 32))
    # DA3's variant: scale factor with offset 0.1 and no antialias gives a different table
    da3_like = _vit(interpolate_offset=0.1)
    with torch.no_grad():
        da3_like.pos_embed.copy_(vit.pos_embed)
    other = da3_like.interpolate_pos_embed(3, 5)
    assert other.shape == table.shape
    assert (other - table).abs().max() > 1e-3


def test_checkpoint_names_and_qk_norm_start() -> None:
    vit = _vit(num_register_tokens=4, qk_norm_start=1)
    names = set(vit.state_dict())
    assert {
        "cls_token",
        "register_tokens",
        "pos_embed",
        "patch_embed.proj.weight",
        "norm.weight",
    } <= names
    assert "blocks.1.attn.q_norm.weight" in names and "blocks.0.attn.q_norm.weight" not in names
    assert "blocks.0.ls1.gamma" in names
    assert "mask_token" not in names
    assert "register_tokens" not in _vit().state_dict()


def test_rejects_size_not_multiple_of_patch() -> None:
    with pytest.raises(ImageShapeError, match="multiple of the patch size"):
        _vit()(torch.rand(1, 3, 28, 30))

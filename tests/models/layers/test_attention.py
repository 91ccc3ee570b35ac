"""Attention: the reference math, and the map / track uses agreeing with a masked full pass."""

from __future__ import annotations

import pytest
import torch

from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.models.layers.attention import Attention, keyframe_query_mask
from kvtracker_sdk.models.layers.block import Block
from kvtracker_sdk.models.layers.rope2d import grid_positions, rope_table

DIM, HEADS, T = 32, 2, 7  # tokens per "frame": 1 prefix + 2x3 patches


def _rope(frames: int):
    return rope_table(grid_positions(2, 3, num_prefix_tokens=1), DIM // HEADS).repeat(frames)


def _randomise(module: torch.nn.Module, seed: int) -> None:
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(
                torch.randn(p.shape, generator=generator) * 0.3 + (1.0 if p.dim() == 1 else 0.0)
            )


def test_forward_matches_explicit_softmax() -> None:
    torch.manual_seed(0)
    attn = Attention(DIM, HEADS, qk_norm=True)
    _randomise(attn, 1)
    x = torch.randn(2, 3 * T, DIM)
    rope = _rope(3)
    q, k, v = attn.project(x, rope)
    weights = torch.softmax(q @ k.transpose(-1, -2) / (DIM // HEADS) ** 0.5, dim=-1)
    expected = attn.proj((weights @ v).transpose(1, 2).reshape(2, 3 * T, DIM))
    torch.testing.assert_close(attn(x, rope=rope), expected, atol=1e-5, rtol=0)
    # project applies k_norm then RoPE
    raw_k = attn.qkv(x).reshape(2, 3 * T, 3, HEADS, DIM // HEADS)[:, :, 1].transpose(1, 2)
    torch.testing.assert_close(k, rope.apply(attn.k_norm(raw_k)), atol=1e-6, rtol=0)


def test_keyframe_query_mask() -> None:
    mask = keyframe_query_mask(4, 2, 3)
    assert mask.shape == (10, 10) and mask.dtype == torch.bool
    assert mask[:4, :4].all() and not mask[:4, 4:].any()  # keyframes see only keyframes
    assert mask[4:, :4].all()  # queries see every keyframe token
    assert mask[4:7, 4:7].all() and not mask[4:7, 7:].any()  # each query sees itself only
    assert mask[7:, 7:].all() and not mask[7:, 4:7].any()
    assert torch.equal(keyframe_query_mask(4, 2, 3, queries_only=True), mask[4:])


@pytest.mark.parametrize("num_queries", [1, 3])
def test_block_track_equals_masked_forward(num_queries: int) -> None:
    torch.manual_seed(2)
    block = Block(DIM, HEADS, qk_norm=True, layerscale_init=0.5)
    _randomise(block, 3)
    keyframes, cached = 2, 2 * T
    x = torch.randn(1, cached + num_queries * T, DIM)
    mask = keyframe_query_mask(cached, num_queries, T)
    full = block(x, rope=_rope(keyframes + num_queries), attn_mask=mask)

    mapped, k, v = block.forward_map(x[:, :cached], rope=_rope(keyframes))
    torch.testing.assert_close(mapped, full[:, :cached], atol=1e-5, rtol=1e-6)  # values O(30)

    capacity = cached + num_queries * T + 5
    key_buffer = torch.full((1, HEADS, capacity, DIM // HEADS), float("nan"))
    value_buffer = key_buffer.clone()
    key_buffer[:, :, :cached], value_buffer[:, :, :cached] = k, v
    track_mask = mask[cached:] if num_queries > 1 else None
    tracked = block.forward_track(
        x[:, cached:],
        key_buffer,
        value_buffer,
        cached,
        rope=_rope(num_queries),
        attn_mask=track_mask,
    )
    torch.testing.assert_close(tracked, full[:, cached:], atol=1e-5, rtol=1e-6)
    # the cached part is untouched, the query's K/V went to the scratch region, the rest is unread
    torch.testing.assert_close(key_buffer[:, :, :cached], k, atol=0, rtol=0)
    assert torch.isfinite(key_buffer[:, :, cached : cached + num_queries * T]).all()
    assert torch.isnan(key_buffer[:, :, cached + num_queries * T :]).all()


def test_track_without_cache_differs() -> None:
    torch.manual_seed(4)
    block = Block(DIM, HEADS, qk_norm=True, layerscale_init=0.5)
    _randomise(block, 5)
    x = torch.randn(1, 3 * T, DIM)
    full = block(x, rope=_rope(3), attn_mask=keyframe_query_mask(2 * T, 1, T))
    empty = torch.empty(1, HEADS, T, DIM // HEADS)
    alone = block.forward_track(x[:, 2 * T :], empty, empty.clone(), 0, rope=_rope(1))
    assert (alone - full[:, 2 * T :]).abs().max() > 1e-2


def test_names_and_errors() -> None:
    block = Block(DIM, HEADS, qk_norm=True, layerscale_init=1.0)
    names = set(block.state_dict())
    assert {"attn.qkv.weight", "attn.q_norm.weight", "attn.k_norm.bias", "attn.proj.bias"} <= names
    assert {
        "ls1.gamma",
        "ls2.gamma",
        "mlp.fc1.weight",
        "mlp.fc2.bias",
        "norm1.weight",
        "norm2.bias",
    } <= names
    plain = Block(DIM, HEADS)
    assert not any("ls1" in n or "q_norm" in n for n in plain.state_dict())
    with pytest.raises(ConfigError, match="not divisible"):
        Attention(30, 4)

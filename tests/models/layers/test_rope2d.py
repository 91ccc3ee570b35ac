"""RoPE2D: the formula, its relative-position property, the bf16 rounding and the position grid."""

from __future__ import annotations

import math

import pytest
import torch

from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.models.layers.rope2d import grid_positions, rope_table


def naive_rope2d(x: torch.Tensor, positions: torch.Tensor, base: float) -> torch.Tensor:
    """Per-channel-pair rotation written out with loops (the formula of pi3-architecture.md)."""
    out = torch.empty_like(x)
    head_dim = x.shape[-1]
    half, quarter = head_dim // 2, head_dim // 4
    for axis in range(2):  # 0: y rotates the first half, 1: x the second
        for j in range(quarter):
            freq = base ** (-2 * j / half)
            angle = positions[:, axis].double() * freq  # [L]
            cos, sin = torch.cos(angle).to(x.dtype), torch.sin(angle).to(x.dtype)
            a = axis * half + j  # channel a pairs with a + quarter
            b = a + quarter
            out[..., a] = x[..., a] * cos - x[..., b] * sin
            out[..., b] = x[..., b] * cos + x[..., a] * sin
    return out


@pytest.mark.parametrize("head_dim", [8, 24, 64])
def test_rope_matches_naive_formula(head_dim: int) -> None:
    torch.manual_seed(0)
    positions = grid_positions(5, 7, num_prefix_tokens=3)
    x = torch.randn(2, 3, positions.shape[0], head_dim)
    table = rope_table(positions, head_dim, base=100.0)
    # fp32 angles vs float64 angles: tolerance 1e-5 on O(1) values
    torch.testing.assert_close(table.apply(x), naive_rope2d(x, positions, 100.0), atol=1e-5, rtol=0)


def test_rope_scores_depend_only_on_relative_position() -> None:
    torch.manual_seed(1)
    q, k = torch.randn(1, 1, 2, 32), torch.randn(1, 1, 2, 32)
    pos_a = torch.tensor([[3, 4], [1, 9]])
    pos_b = pos_a + torch.tensor([5, -2])  # same offset on both tokens
    score_a = (
        rope_table(pos_a[:1], 32).apply(q[..., :1, :])
        * rope_table(pos_a[1:], 32).apply(k[..., 1:, :])
    ).sum()
    score_b = (
        rope_table(pos_b[:1], 32).apply(q[..., :1, :])
        * rope_table(pos_b[1:], 32).apply(k[..., 1:, :])
    ).sum()
    torch.testing.assert_close(score_a, score_b, atol=1e-4, rtol=0)
    # and it does depend on the offset itself
    pos_c = torch.tensor([[3, 4], [2, 9]])
    score_c = (
        rope_table(pos_c[:1], 32).apply(q[..., :1, :])
        * rope_table(pos_c[1:], 32).apply(k[..., 1:, :])
    ).sum()
    assert abs(float(score_a - score_c)) > 1e-3


def test_bf16_table_rounds_angles_before_cos() -> None:
    positions = grid_positions(37, 37)
    table = rope_table(positions, 64, dtype=torch.bfloat16)
    assert table.cos.dtype == torch.bfloat16
    inv_freq = 1.0 / (100.0 ** (torch.arange(0, 32, 2, dtype=torch.float32) / 32))
    angles = (positions[:, :1].float() * inv_freq).to(torch.bfloat16)  # y half, first 16 channels
    torch.testing.assert_close(table.cos[:, :16], angles.cos(), atol=0, rtol=0)
    # rounding the angle first is not the same as rounding the cosine of the exact angle
    exact = (positions[:, :1].float() * inv_freq).cos().to(torch.bfloat16)
    assert not torch.equal(table.cos[:, :16], exact)


def test_grid_positions_layout() -> None:
    positions = grid_positions(2, 3, num_prefix_tokens=2)
    expected = [[0, 0], [0, 0], [1, 1], [1, 2], [1, 3], [2, 1], [2, 2], [2, 3]]
    assert positions.tolist() == expected
    assert positions.dtype == torch.int64


def test_repeat_tiles_frames_and_identity_at_origin() -> None:
    table = rope_table(grid_positions(2, 2, num_prefix_tokens=1), 16)
    tiled = table.repeat(3)
    assert tiled.num_tokens == 3 * table.num_tokens
    torch.testing.assert_close(tiled.cos[5:10], table.cos, atol=0, rtol=0)
    # prefix tokens at (0, 0) are not rotated
    x = torch.randn(1, 5, 16)
    torch.testing.assert_close(table.apply(x)[:, 0], x[:, 0], atol=0, rtol=0)
    assert math.isclose(float(table.cos[0].min()), 1.0)


def test_head_dim_must_be_multiple_of_four() -> None:
    with pytest.raises(ConfigError, match="divisible by 4"):
        rope_table(grid_positions(2, 2), 30)

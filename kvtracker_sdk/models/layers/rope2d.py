"""2-D rotary position embedding (RoPE2D) with tables that do not depend on the data.

Each token has an integer (y, x) position. For a head of width ``D`` (a multiple of 4), the first
``D/2`` channels are rotated by ``y`` and the last ``D/2`` by ``x``. Inside each half of width
``h = D/2`` there are ``h/2`` frequencies ``base^(-2j/h)`` and channel ``i`` is paired with channel
``i + h/2`` ("rotate half")::

    angle[p, j] = pos[p] * base^(-2j/h)           j = 0 .. h/2-1
    table       = cat(angle, angle)                # h wide, per half
    out         = x * cos(table) + rotate_half(x) * sin(table),   rotate_half(u) = cat(-u2, u1)

This is the RoPE2D of CroCo/DUSt3R/Pi3/DA3 (base 100 in Pi3 and DA3), re-derived from the formula.

Why tables are computed from positions directly (instead of a lookup table sized by
``positions.max()`` as the reference code does): the cos/sin are then a pure function of the
position tensor, so exporters see no data-dependent shape and ONNX graphs keep dynamic sizes.

Precision: under bf16 the reference code rounds the *angles* to bf16 before taking cos/sin (the
released weights were trained that way). ``rope_table(..., dtype=torch.bfloat16)`` reproduces this;
in fp32 the table is bit-identical to the reference one.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from kvtracker_sdk.errors import ConfigError

__all__ = ["RopeTable", "grid_positions", "rope_table"]


@dataclass(frozen=True)
class RopeTable:
    """cos/sin of every token's rotation angles, each [L, D] in the compute dtype."""

    cos: torch.Tensor
    sin: torch.Tensor

    @property
    def num_tokens(self) -> int:
        return int(self.cos.shape[0])

    def repeat(self, times: int) -> RopeTable:
        """The table of ``times`` frames laid out frame-major (positions carry no frame index)."""
        return RopeTable(self.cos.repeat(times, 1), self.sin.repeat(times, 1))

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        """Rotate ``x`` [..., L, D] (e.g. [B, heads, L, D]); returns the same shape and dtype."""
        quarter = x.shape[-1] // 4
        # [..., half (y | x), pair member (first | second), quarter]
        parts = x.unflatten(-1, (2, 2, quarter))
        rotated = torch.cat((-parts[..., 1:, :], parts[..., :1, :]), dim=-2).flatten(-3)
        return x * self.cos + rotated * self.sin


def grid_positions(
    grid_h: int,
    grid_w: int,
    *,
    num_prefix_tokens: int = 0,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """(y, x) positions of one frame's tokens: [num_prefix_tokens + grid_h * grid_w, 2] int64.

    Prefix tokens (registers, camera token) sit at (0, 0); the patch in row ``r``, column ``c``
    (row-major order) at (r + 1, c + 1).
    """
    rows = torch.arange(1, grid_h + 1, device=device)
    cols = torch.arange(1, grid_w + 1, device=device)
    patches = torch.stack(torch.meshgrid(rows, cols, indexing="ij"), dim=-1).reshape(-1, 2)
    prefix = torch.zeros(num_prefix_tokens, 2, dtype=patches.dtype, device=device)
    return torch.cat((prefix, patches), dim=0)


def rope_table(
    positions: torch.Tensor,
    head_dim: int,
    *,
    base: float = 100.0,
    dtype: torch.dtype = torch.float32,
) -> RopeTable:
    """cos/sin [L, head_dim] for ``positions`` [L, 2] (y, x) integers.

    With a reduced-precision ``dtype`` the angles are rounded to it before cos/sin, as the
    reference implementation does under bf16.
    """
    if head_dim % 4 != 0:
        raise ConfigError(f"RoPE2D needs head_dim divisible by 4, got {head_dim}")
    half = head_dim // 2
    exponents = torch.arange(0, half, 2, device=positions.device, dtype=torch.float32) / half
    inv_freq = 1.0 / (base**exponents)  # [half / 2]
    angles = positions.to(torch.float32).unsqueeze(-1) * inv_freq  # [L, 2 (y, x), half / 2]
    angles = angles.to(dtype)
    table = torch.cat((angles, angles), dim=-1).flatten(-2)  # [L, head_dim]: y half, then x half
    return RopeTable(table.cos(), table.sin())

"""DINOv2 vision transformer (ViT/14) with optional register tokens and pos-embed interpolation.

Tokens of one image [3, H, W] (H, W multiples of the patch size p)::

    patch conv -> [h*w, dim]  (h = H/p, w = W/p, row-major)
    prepend cls_token                          -> [1 + h*w, dim]
    add pos_embed, its grid resized to (h, w)  (bicubic; options below)
    insert register_tokens after cls           -> [1 + R + h*w, dim]
    pre-norm blocks, final norm

Options that differ between the families that use this encoder:

| option | Pi3 (ViT-L/14-reg4) | Depth Anything 3 |
|---|---|---|
| ``num_register_tokens`` | 4 | 0 |
| ``interpolate_antialias`` | True | False |
| ``interpolate_offset`` | 0 (resize with ``size=(h, w)``) | 0.1 (``scale_factor=((h+0.1)/g, (w+0.1)/g)``) |
| ``final_norm_eps`` | 1e-6 | 1e-5 |
| ``qk_norm_start`` | None | first block with qk-norm (DA3 runs its own block loop) |
| ``ffn`` | "mlp" | "mlp"; "swiglu" for the ViT-g backbone of DA3-Giant |

The checkpoint names are DINOv2's (``cls_token``, ``register_tokens``, ``pos_embed``,
``patch_embed.proj``, ``blocks.{i}``, ``norm``); there is no ``mask_token`` (neither Pi3 nor DA3
checkpoints have one).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from kvtracker_sdk.models.layers.block import Block
from kvtracker_sdk.models.layers.patch_embed import PatchEmbed
from kvtracker_sdk.models.layers.symbolic_sizes import bicubic_resize_matrix, size_tensor

__all__ = ["DinoViT"]


class DinoViT(nn.Module):
    """DINOv2 ViT; ``forward`` returns the normed patch tokens [B, h*w, dim]."""

    def __init__(
        self,
        *,
        embed_dim: int,
        depth: int,
        num_heads: int,
        patch_size: int = 14,
        mlp_ratio: float = 4.0,
        pos_embed_grid: int = 37,
        num_register_tokens: int = 0,
        interpolate_antialias: bool = False,
        interpolate_offset: float = 0.0,
        layerscale_init: float | None = 1.0,
        qk_norm_start: int | None = None,
        norm_eps: float = 1e-6,
        final_norm_eps: float = 1e-6,
        ffn: str = "mlp",
    ) -> None:
        super().__init__()
        self.embed_dim = embed_dim
        self.patch_size = patch_size
        self.pos_embed_grid = pos_embed_grid
        self.num_register_tokens = num_register_tokens
        self.interpolate_antialias = interpolate_antialias
        self.interpolate_offset = interpolate_offset

        self.patch_embed = PatchEmbed(patch_size, embed_dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, embed_dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + pos_embed_grid**2, embed_dim))
        self.register_tokens = (
            nn.Parameter(torch.zeros(1, num_register_tokens, embed_dim)) if num_register_tokens else None
        )
        self.blocks = nn.ModuleList(
            Block(
                embed_dim,
                num_heads,
                mlp_ratio=mlp_ratio,
                qk_norm=qk_norm_start is not None and i >= qk_norm_start,
                layerscale_init=layerscale_init,
                norm_eps=norm_eps,
                ffn=ffn,
            )
            for i in range(depth)
        )
        self.norm = nn.LayerNorm(embed_dim, eps=final_norm_eps)
        self._init_tokens()

    def _init_tokens(self) -> None:
        # Only matters for models built without a checkpoint (tests): small random tokens.
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        nn.init.normal_(self.cls_token, std=1e-6)
        if self.register_tokens is not None:
            nn.init.normal_(self.register_tokens, std=1e-6)

    @property
    def num_prefix_tokens(self) -> int:
        """cls + registers, before the patch tokens."""
        return 1 + self.num_register_tokens

    def interpolate_pos_embed(self, grid_h: int, grid_w: int) -> torch.Tensor:
        """[1, 1 + grid_h*grid_w, dim]: cls position, then the grid resized to (grid_h, grid_w).

        The resize runs in fp32 (as DINOv2 does) and the result is cast to the parameter dtype.
        While ``torch.export`` traces (the ONNX exporter), the resize without antialias runs as
        two interpolation matrices built from the (symbolic) grid size, the same function to
        ~1e-5: ``F.interpolate`` would fix the grid size to the example's.
        """
        side = self.pos_embed_grid
        if torch.compiler.is_exporting() and not self.interpolate_antialias:
            return self._exportable_pos_embed(grid_h, grid_w)
        if (grid_h, grid_w) == (side, side):
            return self.pos_embed
        table = self.pos_embed.float()
        cls_pos, grid = table[:, :1], table[:, 1:]
        grid = grid.reshape(1, side, side, -1).permute(0, 3, 1, 2)  # [1, dim, side, side]
        if self.interpolate_offset:
            # DINOv2's historical kludge: a scale factor slightly above the target size
            scale = ((grid_h + self.interpolate_offset) / side, (grid_w + self.interpolate_offset) / side)
            grid = F.interpolate(grid, scale_factor=scale, mode="bicubic", antialias=self.interpolate_antialias)
        else:
            grid = F.interpolate(grid, size=(grid_h, grid_w), mode="bicubic", antialias=self.interpolate_antialias)
        grid = grid.permute(0, 2, 3, 1).reshape(1, grid_h * grid_w, -1)  # row-major over (h, w)
        return torch.cat((cls_pos, grid), dim=1).to(self.pos_embed.dtype)

    def _exportable_pos_embed(self, grid_h: int, grid_w: int) -> torch.Tensor:
        """``interpolate_pos_embed`` without antialias, as ``M_h @ grid @ M_wᵀ`` (see
        ``symbolic_sizes.py``); at the native grid size (both sides) the matrices are the
        identity, as the eager path returns the table unresized."""
        side = self.pos_embed_grid
        table = self.pos_embed.float()
        cls_pos, grid = table[0, :1], table[0, 1:].reshape(side, side, -1)
        rows, cols = size_tensor(grid_h, table.device), size_tensor(grid_w, table.device)
        native = (rows == side) & (cols == side)

        def matrix(size: int, target: torch.Tensor) -> torch.Tensor:
            # PyTorch reads the source at steps of 1 / scale_factor, or in / out without one
            step = side / (target + self.interpolate_offset)
            step = torch.where(native, torch.ones_like(step), step)
            return bicubic_resize_matrix(size, side, step, table.device)

        resized = torch.einsum("hi,ijc,wj->hwc", matrix(grid_h, rows), grid, matrix(grid_w, cols))
        patches = resized.reshape(grid_h * grid_w, -1)
        return torch.cat((cls_pos, patches), dim=0).unsqueeze(0).to(self.pos_embed.dtype)

    def prepare_tokens(self, images: torch.Tensor) -> torch.Tensor:
        """Normalised images [B, 3, H, W] -> tokens [B, 1 + R + h*w, dim] (cls, registers, patches)."""
        batch = images.shape[0]
        grid_h, grid_w = images.shape[-2] // self.patch_size, images.shape[-1] // self.patch_size
        patches = self.patch_embed(images)
        tokens = torch.cat((self.cls_token.expand(batch, -1, -1), patches), dim=1)
        tokens = tokens + self.interpolate_pos_embed(grid_h, grid_w)
        if self.register_tokens is None:
            return tokens
        return torch.cat((tokens[:, :1], self.register_tokens.expand(batch, -1, -1), tokens[:, 1:]), dim=1)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Normalised images [B, 3, H, W] -> normed patch tokens [B, h*w, dim] (cls/registers dropped)."""
        tokens = self.prepare_tokens(images)
        for block in self.blocks:
            tokens = block(tokens)
        return self.norm(tokens)[:, self.num_prefix_tokens :]

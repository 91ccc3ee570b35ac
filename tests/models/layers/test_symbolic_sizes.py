"""Export-friendly size arithmetic: the bicubic resize matrices and the exportable pos-embed
resize equal PyTorch's ``F.interpolate`` (the eager path), and keep sizes symbolic in export."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from kvtracker_sdk.models.layers.symbolic_sizes import bicubic_resize_matrix, size_tensor
from kvtracker_sdk.models.layers.vit_encoder import DinoViT

# PyTorch's kernel computes its source coordinates in float32; ours too, but its summation order
# differs: measured <= 9e-6 on N(0, 1) grids (values up to ~4), i.e. ~2e-6 relative
TOLERANCE = 2e-5


@pytest.mark.parametrize("size", [(1, 2), (8, 11), (9, 12), (37, 37), (50, 60)])
def test_bicubic_matrices_equal_interpolate_with_a_scale_factor(size: tuple[int, int]) -> None:
    generator = torch.Generator().manual_seed(0)
    grid = torch.randn(1, 6, 37, 37, generator=generator)
    scale = ((size[0] + 0.1) / 37, (size[1] + 0.1) / 37)
    expected = F.interpolate(grid, scale_factor=scale, mode="bicubic", antialias=False)[0]
    rows, cols = (
        bicubic_resize_matrix(n, 37, size_tensor(37) / (size_tensor(n) + 0.1)) for n in size
    )
    got = torch.einsum("hi,cij,wj->chw", rows, grid[0], cols)
    torch.testing.assert_close(got, expected, atol=TOLERANCE, rtol=0)


def test_bicubic_matrices_equal_interpolate_to_a_size() -> None:
    generator = torch.Generator().manual_seed(1)
    grid = torch.randn(1, 3, 10, 10, generator=generator)
    expected = F.interpolate(grid, size=(7, 13), mode="bicubic", antialias=False)[0]
    rows = bicubic_resize_matrix(7, 10, size_tensor(10) / size_tensor(7))
    cols = bicubic_resize_matrix(13, 10, size_tensor(10) / size_tensor(13))
    got = torch.einsum("hi,cij,wj->chw", rows, grid[0], cols)
    torch.testing.assert_close(got, expected, atol=TOLERANCE, rtol=0)


@pytest.mark.parametrize("offset", [0.0, 0.1])
@pytest.mark.parametrize("size", [(3, 5), (6, 6), (6, 4), (8, 4)])
def test_exportable_pos_embed_equals_the_eager_one(offset: float, size: tuple[int, int]) -> None:
    torch.manual_seed(2)
    vit = DinoViT(
        embed_dim=8, depth=1, num_heads=2, pos_embed_grid=6, interpolate_offset=offset
    )
    with torch.no_grad():
        vit.pos_embed.normal_()
    expected = vit.interpolate_pos_embed(*size)
    torch.testing.assert_close(vit._exportable_pos_embed(*size), expected, atol=TOLERANCE, rtol=0)
    if size == (6, 6):  # the native grid is used as it is
        torch.testing.assert_close(vit._exportable_pos_embed(*size), vit.pos_embed, atol=0, rtol=0)


def test_exported_pos_embed_keeps_the_grid_symbolic() -> None:
    torch.manual_seed(3)
    vit = DinoViT(embed_dim=8, depth=1, num_heads=2, pos_embed_grid=6, interpolate_offset=0.1)

    class Tokens(torch.nn.Module):
        def forward(self, images: torch.Tensor) -> torch.Tensor:
            return vit.prepare_tokens(images)

    rows, cols = torch.export.Dim("rows"), torch.export.Dim("cols")
    program = torch.export.export(
        Tokens(), (torch.rand(1, 3, 42, 56),), dynamic_shapes=({2: 14 * rows, 3: 14 * cols},)
    )
    images = torch.rand(1, 3, 70, 28)  # another grid than the example's
    torch.testing.assert_close(
        program.module()(images), vit.prepare_tokens(images), atol=TOLERANCE, rtol=0
    )

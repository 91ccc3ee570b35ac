"""Pi3 heads: SVD orthogonalisation, pixel-shuffle layout, camera pooling."""

from __future__ import annotations

import torch

from kvtracker_sdk.models.pi3.heads import CameraHead, PixelShuffleHead, rotation_from_matrix9


def test_rotation_from_matrix9_is_a_proper_rotation() -> None:
    generator = torch.Generator().manual_seed(0)
    raw = torch.randn(64, 9, generator=generator)
    rotations = rotation_from_matrix9(raw)
    eye = torch.eye(3).expand(64, 3, 3)
    torch.testing.assert_close(rotations @ rotations.transpose(1, 2), eye, atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.linalg.det(rotations), torch.ones(64), atol=1e-5, rtol=0)
    # about half of the random matrices are reflections (det < 0): they still give det +1
    assert (torch.linalg.det(raw.reshape(-1, 3, 3)) < 0).sum() > 10


def test_rotation_input_is_kept_and_rows_are_normalised() -> None:
    angle = torch.tensor(0.7)
    rotation = torch.tensor(
        [
            [torch.cos(angle), -torch.sin(angle), 0.0],
            [torch.sin(angle), torch.cos(angle), 0.0],
            [0.0, 0.0, 1.0],
        ]
    )
    scaled_rows = rotation * torch.tensor([[2.0], [0.5], [3.0]])  # row norms are divided out
    torch.testing.assert_close(
        rotation_from_matrix9(scaled_rows.reshape(1, 9))[0], rotation, atol=1e-6, rtol=0
    )


def test_pixel_shuffle_layout() -> None:
    patch, channels, grid_h, grid_w = 2, 3, 2, 3
    head = PixelShuffleHead(channels * patch * patch, channels, patch)
    with torch.no_grad():
        head.proj.weight.copy_(torch.eye(channels * patch * patch))
        head.proj.bias.zero_()
    tokens = torch.randn(1, grid_h * grid_w, channels * patch * patch)
    pixels = head(tokens, grid_h, grid_w)
    assert pixels.shape == (1, grid_h * patch, grid_w * patch, channels)
    for y in range(grid_h):
        for x in range(grid_w):
            for c in range(channels):
                for dy in range(patch):
                    for dx in range(patch):
                        channel = c * patch * patch + dy * patch + dx  # official layout
                        got = pixels[0, y * patch + dy, x * patch + dx, c]
                        assert got == tokens[0, y * grid_w + x, channel]


def test_camera_head_pools_over_tokens() -> None:
    torch.manual_seed(0)
    head = CameraHead(16).eval()
    tokens = torch.randn(2, 12, 16)
    with torch.no_grad():
        poses = head(tokens)
        shuffled = head(tokens[:, torch.randperm(12)])
    assert poses.shape == (2, 4, 4)
    torch.testing.assert_close(poses, shuffled, atol=1e-5, rtol=0)  # mean pooling: order-free
    torch.testing.assert_close(poses[:, 3], torch.tensor([0.0, 0.0, 0.0, 1.0]).expand(2, 4))
    assert not torch.allclose(poses[0], poses[1])

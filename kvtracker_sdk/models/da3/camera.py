"""DA3's cameras: the 9-number pose encoding, the camera decoder and the pose encoder.

``pose_enc = [t (3), q (4, xyzw, scalar last, need not be unit), fov_h, fov_w]`` describes a
camera-to-world pose ``[R(q) | t]`` (OpenCV axes) and a pinhole camera with the principal point
at the image centre::

    fy = (H / 2) / max(tan(fov_h / 2), 1e-6)      fx = (W / 2) / max(tan(fov_w / 2), 1e-6)
    cx = W / 2                                     cy = H / 2

Pixel coordinates follow DA3: pixel (row i, column j) is at (u, v) = (j, i). The conversions are
torch functions batched over leading dims.

- ``CameraDecoder`` (``cam_dec``): per view, a two-layer ReLU MLP on the camera token [2C]
  (token 0 of ``cat(local, global)`` at the last out layer), then three linear heads:
  translation (3), quaternion xyzw (4, unnormalised) and ReLU(fov) (2) -> ``pose_enc`` [9].
- ``CameraEncoder`` (``cam_enc``): pose conditioning. Known cameras (world-to-camera
  extrinsics and intrinsics) become per-view tokens [C] that replace the learned camera tokens
  at block ``alt_start``: pose encoding -> MLP (9 -> C/2 -> C, GELU) -> LayerNorm -> four
  transformer blocks attending across the views (LayerScale 0.01, LayerNorm eps 1e-5) ->
  LayerNorm.

Both modules run in fp32, as the official code runs them with autocast disabled.
"""

from __future__ import annotations

import torch
from torch import nn

from kvtracker_sdk.models.da3.config import DA3CameraEncoderConfig
from kvtracker_sdk.models.layers.block import Block
from kvtracker_sdk.models.layers.mlp import Mlp

__all__ = [
    "CameraDecoder",
    "CameraEncoder",
    "decode_pose_encoding",
    "encode_pose_encoding",
    "invert_rigid",
    "matrix_to_quat_xyzw",
    "quat_xyzw_to_matrix",
]


def quat_xyzw_to_matrix(quat: torch.Tensor) -> torch.Tensor:
    """[..., 4] quaternions (x, y, z, w), any non-zero norm -> rotations [..., 3, 3].

    Dividing by |q|² (``s = 2 / |q|²``) makes the result a rotation for unnormalised q.
    """
    x, y, z, w = quat.unbind(-1)
    s = 2.0 / (quat * quat).sum(-1)
    rows = (
        1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w),
        s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w),
        s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y),
    )  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(*quat.shape[:-1], 3, 3)


def matrix_to_quat_xyzw(rotation: torch.Tensor) -> torch.Tensor:
    """Rotations [..., 3, 3] -> unit quaternions [..., 4] (x, y, z, w) with w >= 0.

    Each of 2|w|, 2|x|, 2|y|, 2|z| follows from the diagonal; the quaternion is read from the
    row of the largest one (the best-conditioned division), as in Shepperd's method.
    """
    m = rotation.reshape(*rotation.shape[:-2], 9).unbind(-1)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m
    twice_abs = torch.sqrt(
        torch.stack(
            (1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22),
            dim=-1,
        ).clamp(min=0)
    )  # [..., 4]: 2|w|, 2|x|, 2|y|, 2|z|
    # row r holds (w, x, y, z) * 2 * twice_abs[r], computed from off-diagonal sums and differences
    candidates = torch.stack(
        (
            torch.stack((twice_abs[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01), dim=-1),
            torch.stack((m21 - m12, twice_abs[..., 1] ** 2, m10 + m01, m02 + m20), dim=-1),
            torch.stack((m02 - m20, m10 + m01, twice_abs[..., 2] ** 2, m12 + m21), dim=-1),
            torch.stack((m10 - m01, m20 + m02, m21 + m12, twice_abs[..., 3] ** 2), dim=-1),
        ),
        dim=-2,
    ) / (2.0 * twice_abs.clamp(min=0.1)).unsqueeze(-1)
    best = twice_abs.argmax(dim=-1)[..., None, None].expand(*rotation.shape[:-2], 1, 4)
    wxyz = candidates.gather(-2, best).squeeze(-2)
    xyzw = wxyz[..., [1, 2, 3, 0]]
    return torch.where(xyzw[..., 3:] < 0, -xyzw, xyzw)


def invert_rigid(transform: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms [..., 3 or 4, 4]: ``[Rᵀ | -Rᵀ t]`` (bottom row kept if present)."""
    rotation_t = transform[..., :3, :3].mT
    top = torch.cat((rotation_t, -rotation_t @ transform[..., :3, 3:]), dim=-1)
    return torch.cat((top, transform[..., 3:, :]), dim=-2)


def decode_pose_encoding(
    pose_enc: torch.Tensor, image_size: tuple[int, int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """[..., 9] -> (camera-to-world [..., 3, 4], intrinsics [..., 3, 3]) for images (H, W)."""
    height, width = image_size
    translation, quat, fov_h, fov_w = (
        pose_enc[..., :3],
        pose_enc[..., 3:7],
        pose_enc[..., 7],
        pose_enc[..., 8],
    )
    cam_to_world = torch.cat((quat_xyzw_to_matrix(quat), translation.unsqueeze(-1)), dim=-1)
    intrinsics = torch.zeros(
        *pose_enc.shape[:-1], 3, 3, dtype=pose_enc.dtype, device=pose_enc.device
    )
    intrinsics[..., 0, 0] = (width / 2.0) / torch.clamp(torch.tan(fov_w / 2.0), min=1e-6)
    intrinsics[..., 1, 1] = (height / 2.0) / torch.clamp(torch.tan(fov_h / 2.0), min=1e-6)
    intrinsics[..., 0, 2] = width / 2
    intrinsics[..., 1, 2] = height / 2
    intrinsics[..., 2, 2] = 1.0
    return cam_to_world, intrinsics


def encode_pose_encoding(
    cam_to_world: torch.Tensor, intrinsics: torch.Tensor, image_size: tuple[int, int]
) -> torch.Tensor:
    """(camera-to-world [..., 3 or 4, 4], intrinsics [..., 3, 3]) -> [..., 9] float32."""
    height, width = image_size
    fov_h = 2 * torch.atan((height / 2) / intrinsics[..., 1, 1])
    fov_w = 2 * torch.atan((width / 2) / intrinsics[..., 0, 0])
    quat = matrix_to_quat_xyzw(cam_to_world[..., :3, :3])
    parts = (cam_to_world[..., :3, 3], quat, fov_h.unsqueeze(-1), fov_w.unsqueeze(-1))
    return torch.cat(parts, dim=-1).float()


POSE_ENCODING_DIM = 9


class CameraDecoder(nn.Module):
    """``cam_dec``: camera tokens [..., dim] -> pose encodings [..., 9] (float32)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.backbone = nn.Sequential(
            nn.Linear(dim, dim), nn.ReLU(), nn.Linear(dim, dim), nn.ReLU()
        )
        self.fc_t = nn.Linear(dim, 3)
        self.fc_qvec = nn.Linear(dim, 4)
        self.fc_fov = nn.Sequential(nn.Linear(dim, 2), nn.ReLU())

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        hidden = self.backbone(tokens).float()
        return torch.cat((self.fc_t(hidden), self.fc_qvec(hidden), self.fc_fov(hidden)), dim=-1)


class CameraEncoder(nn.Module):
    """``cam_enc``: known cameras of N views -> camera tokens [B, N, dim]."""

    def __init__(self, dim: int, config: DA3CameraEncoderConfig) -> None:
        super().__init__()
        self.pose_branch = Mlp(POSE_ENCODING_DIM, dim // 2, dim)
        self.token_norm = nn.LayerNorm(dim)
        self.trunk = nn.Sequential(
            *(
                Block(
                    dim,
                    config.num_heads,
                    mlp_ratio=config.mlp_ratio,
                    layerscale_init=0.01,
                    norm_eps=1e-5,
                )
                for _ in range(config.depth)
            )
        )
        self.trunk_norm = nn.LayerNorm(dim)

    def forward(
        self, extrinsics: torch.Tensor, intrinsics: torch.Tensor, image_size: tuple[int, int]
    ) -> torch.Tensor:
        """World-to-camera [B, N, 3 or 4, 4] and intrinsics [B, N, 3, 3] of images (H, W) -> [B, N, dim]."""
        pose_enc = encode_pose_encoding(
            invert_rigid(extrinsics.float()), intrinsics.float(), image_size
        )
        tokens = self.token_norm(self.pose_branch(pose_enc))
        return self.trunk_norm(self.trunk(tokens))

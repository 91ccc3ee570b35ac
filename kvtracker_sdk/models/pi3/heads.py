"""Pi3's per-frame output heads: head decoders, pixel-shuffle point/confidence heads, camera head.

Nothing here mixes frames: every module maps [frames, tokens, channels] to per-frame outputs, so
tracking one frame runs exactly the modules a full forward runs for that frame.

- ``HeadDecoder`` (``point_decoder``, ``conf_decoder``, ``camera_decoder``): ``projects`` Linear,
  ``blocks`` like the decoder's but without qk-norm and LayerScale (same RoPE2D positions), then
  ``linear_out``. Input: the decoder's concat(second-to-last, last block) tokens.
- ``PixelShuffleHead`` (``point_head``, ``conf_head``): Linear to ``channels * p * p`` per patch
  token, laid out to pixels with channel index ``c*p*p + dy*p + dx`` (``F.pixel_shuffle``).
- ``CameraHead``: two residual MLP blocks per token, mean over patch tokens, an MLP, then a
  translation (3) and a 3x3 matrix (9) projected onto SO(3) by SVD with det = +1.
  Output: camera-to-world [frames, 4, 4], OpenCV axes.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from kvtracker_sdk.models.layers.block import Block
from kvtracker_sdk.models.layers.rope2d import RopeTable

__all__ = [
    "CameraHead",
    "HeadDecoder",
    "PixelShuffleHead",
    "project_pose_rotations",
    "rotation_from_matrix9",
]


class HeadDecoder(nn.Module):
    """[frames, T, in_dim] -> [frames, T, out_dim]; attention within each frame only."""

    def __init__(
        self,
        in_dim: int,
        out_dim: int,
        *,
        embed_dim: int,
        depth: int,
        num_heads: int,
        mlp_ratio: float,
    ) -> None:
        super().__init__()
        self.projects = nn.Linear(in_dim, embed_dim)
        self.blocks = nn.ModuleList(
            Block(embed_dim, num_heads, mlp_ratio=mlp_ratio, qk_norm=False, layerscale_init=None)
            for _ in range(depth)
        )
        self.linear_out = nn.Linear(embed_dim, out_dim)

    def forward(self, tokens: torch.Tensor, rope: RopeTable) -> torch.Tensor:
        hidden = self.projects(tokens)
        for block in self.blocks:
            hidden = block(hidden, rope=rope)
        return self.linear_out(hidden)


class PixelShuffleHead(nn.Module):
    """Patch tokens [frames, h*w, dim] -> per-pixel values [frames, h*p, w*p, channels]."""

    def __init__(self, dim: int, channels: int, patch_size: int) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Linear(dim, channels * patch_size**2)

    def forward(self, tokens: torch.Tensor, grid_h: int, grid_w: int) -> torch.Tensor:
        frames = tokens.shape[0]
        # [frames, h*w, C*p*p] -> [frames, C*p*p, h, w] -> [frames, C, h*p, w*p]
        features = self.proj(tokens).transpose(1, 2).reshape(frames, -1, grid_h, grid_w)
        return F.pixel_shuffle(features, self.patch_size).permute(0, 2, 3, 1)


class _ResidualMlp(nn.Module):
    """``x + relu(L3(relu(L2(relu(L1 x)))))`` (names ``res_conv1..3`` from the official 1x1 convs)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.res_conv1 = nn.Linear(dim, dim)
        self.res_conv2 = nn.Linear(dim, dim)
        self.res_conv3 = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        update = F.relu(self.res_conv3(F.relu(self.res_conv2(F.relu(self.res_conv1(x))))))
        return x + update


def rotation_from_matrix9(raw: torch.Tensor) -> torch.Tensor:
    """[frames, 9] -> rotations [frames, 3, 3] with det = +1.

    The 3x3 matrix's rows are normalised, then it is replaced by the closest rotation
    ``U diag(1, 1, det(U Vᵀ)) Vᵀ`` from its SVD ``U S Vᵀ`` (the reflection case flips the last
    singular direction).
    """
    matrix = F.normalize(raw.reshape(-1, 3, 3), p=2, dim=-1)
    u, _, vh = torch.linalg.svd(matrix)
    sign = torch.linalg.det(u @ vh)  # [frames], +1 or -1
    flip = torch.ones_like(u[:, 0])  # [frames, 3]
    flip[:, 2] = sign
    return (u * flip.unsqueeze(1)) @ vh


def project_pose_rotations(poses: torch.Tensor) -> torch.Tensor:
    """Poses [..., 4, 4] whose rotation block holds the camera head's raw 3x3 -> the same poses
    with it projected by ``rotation_from_matrix9`` (what ``CameraHead`` does outside a graph)."""
    projected = poses.clone()
    raw = poses[..., :3, :3].reshape(-1, 9)
    projected[..., :3, :3] = rotation_from_matrix9(raw).reshape(*poses.shape[:-2], 3, 3)
    return projected


class CameraHead(nn.Module):
    """Camera patch tokens [frames, h*w, dim] -> camera-to-world poses [frames, 4, 4] (fp32)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.res_conv = nn.ModuleList(_ResidualMlp(dim) for _ in range(2))
        self.more_mlps = nn.Sequential(
            nn.Linear(dim, dim), nn.ReLU(), nn.Linear(dim, dim), nn.ReLU()
        )
        self.fc_t = nn.Linear(dim, 3)
        self.fc_rot = nn.Linear(dim, 9)

    def raw(self, tokens: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """-> the 3x3 before projection [frames, 9] (row-major) and the translation [frames, 3]
        (the exported camera graph stops here: the SVD runs in float64 numpy)."""
        for block in self.res_conv:
            tokens = block(tokens)
        pooled = self.more_mlps(tokens.mean(dim=1))  # mean over the patch tokens: [frames, dim]
        return self.fc_rot(pooled), self.fc_t(pooled)

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        """-> poses [frames, 4, 4]. While a CUDA graph is being captured the rotation block holds
        the raw 3x3 instead: the SVD checks its result on the host, which a graph cannot hold,
        so the graph's runner projects it after each replay (``project_pose_rotations``)."""
        rotation_raw, translation = self.raw(tokens)
        pose = torch.zeros(tokens.shape[0], 4, 4, dtype=translation.dtype, device=translation.device)
        if tokens.is_cuda and torch.cuda.is_current_stream_capturing():
            pose[:, :3, :3] = rotation_raw.reshape(-1, 3, 3)
        else:
            pose[:, :3, :3] = rotation_from_matrix9(rotation_raw)
        pose[:, :3, 3] = translation
        pose[:, 3, 3] = 1.0
        return pose

"""Depth Anything 3 cut into exportable graphs: thin ``nn.Module`` views over one loaded model.

Each module's ``forward`` is the computation of one graph (signatures in ``graph_specs.py``) and
runs the model's own stages (``DA3Backbone.embed_views`` / ``run_per_view`` / ``run_alternating``,
``DualDPT.forward_views``). As for Pi3 (``models/pi3/graphs.py``), the patch grid travels in
tensor shapes ([F, h, w, C]) so that H and W stay dynamic, and the tracking decoder's global step
is ``PastInputsStep`` (``models/layers/alternating.py``: past K/V inputs read by slicing). The
split follows DA3's backbone:

- ``encoder``: ImageNet normalisation, patch and position embedding, and the per-view blocks
  before ``alt_start`` (no camera token yet): the patch tokens entering block ``alt_start``;
- ``decoder_map``: the camera tokens — keyframe 0 gets the **reference** token, the others the
  non-reference one (the pinned reference of ``DA3Backbone.forward_map``) — then the alternating
  blocks with full attention over the keyframes; every global block's K/V is an output;
- ``decoder_track``: one query with the **non-reference** camera token, each global block
  attending over the past K/V and the query itself;
- ``head_camera``: ``cam_dec`` on the camera tokens -> ``pose_enc`` [F, 9] (the pose and the
  intrinsics are decoded by ``conventions.sdk_outputs``, as for the PyTorch passes);
- ``head_depth``: the DualDPT main branch -> depth and its confidence (the auxiliary rays, which
  DA3 drops at inference, are not exported).

The modules hold no weights of their own, so the exported weights are the checkpoint's.
"""

from __future__ import annotations

from typing import cast

import torch
from torch import nn

from kvtracker_sdk.models.da3.backbone import BackboneOutput
from kvtracker_sdk.models.da3.model import DepthAnything3
from kvtracker_sdk.models.layers.alternating import KVRecordingStep, PastInputsStep

__all__ = [
    "CameraHeadGraph",
    "DecoderMapGraph",
    "DecoderTrackGraph",
    "DepthHeadGraph",
    "EncoderGraph",
    "NUM_FEATURE_LEVELS",
]

NUM_FEATURE_LEVELS = 4  # DualDPT reads four out layers


def _views(patch_tokens: torch.Tensor) -> torch.Tensor:
    """[F, h, w, C] -> [1, F, 1 + h*w, C]: one sequence of F views, token 0 a placeholder that
    ``run_alternating`` overwrites with the camera token."""
    frames, grid_h, grid_w, dim = patch_tokens.shape
    patches = patch_tokens.reshape(frames, grid_h * grid_w, dim)
    return torch.cat((torch.zeros_like(patches[:, :1]), patches), dim=1).unsqueeze(0)


def _head_inputs(output: BackboneOutput, grid_h: int, grid_w: int) -> tuple[torch.Tensor, ...]:
    """[1, F] backbone outputs -> ``camera_tokens`` [F, 2C], ``features.{l}`` [F, h, w, 2C]."""
    features = [
        feature[0].reshape(feature.shape[1], grid_h, grid_w, -1) for feature in output.features
    ]
    return (output.camera_tokens[0], *features)


class EncoderGraph(nn.Module):
    """``images`` [F, 3, H, W] RGB in [0, 1] -> ``patch_tokens`` [F, H/14, W/14, C]."""

    def __init__(self, model: DepthAnything3) -> None:
        super().__init__()
        self.model = model

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        backbone = self.model.backbone
        tokens, (grid_h, grid_w) = backbone.embed_views(self.model.normalise(images.unsqueeze(0)))
        blocks = backbone.pretrained.blocks[: backbone.alt_start]
        x = backbone.run_per_view(tokens, blocks)[0]  # [F, T, C]
        return x[:, 1:].reshape(x.shape[0], grid_h, grid_w, x.shape[-1])


class DecoderMapGraph(nn.Module):
    """Keyframes ``patch_tokens`` [N, h, w, C] -> ``camera_tokens`` [N, 2C], ``features.{l}``
    [N, h, w, 2C], then per global block ``present.{i}.key`` and ``.value`` [1, heads, N*T,
    head_dim] (K after k_norm and RoPE; tokens keyframe-major, T = 1 + h*w)."""

    def __init__(self, model: DepthAnything3) -> None:
        super().__init__()
        self.model = model

    def forward(self, patch_tokens: torch.Tensor) -> tuple[torch.Tensor, ...]:
        backbone = self.model.backbone
        views, grid_h, grid_w, _ = patch_tokens.shape
        x = _views(patch_tokens)
        pinned = torch.zeros(1, dtype=torch.long, device=x.device)  # keyframe 0 is the reference
        camera = backbone.learned_camera_tokens(pinned, views)
        step = KVRecordingStep(backbone.global_rope(x).repeat(views))
        output = backbone.run_alternating(x, (grid_h, grid_w), camera, step)
        kv = [tensor for pair in zip(step.keys, step.values, strict=True) for tensor in pair]
        return (*_head_inputs(output, grid_h, grid_w), *kv)


class DecoderTrackGraph(nn.Module):
    """One query frame attending over a cache in every global block.

    ``patch_tokens`` [1, h, w, C], ``past_length`` int64 [] (cached tokens), ``past`` = per
    global block (key, value) [1, heads, capacity >= past_length, head_dim], flattened as key 0,
    value 0, key 1, ... -> ``camera_tokens`` [1, 2C], ``features.{l}`` [1, h, w, 2C].
    """

    def __init__(self, model: DepthAnything3) -> None:
        super().__init__()
        self.model = model

    def forward(
        self, patch_tokens: torch.Tensor, past_length: torch.Tensor, past: tuple[torch.Tensor, ...]
    ) -> tuple[torch.Tensor, ...]:
        backbone = self.model.backbone
        _, grid_h, grid_w, _ = patch_tokens.shape
        x = _views(patch_tokens)
        camera = backbone.pretrained.camera_token[:, 1:]  # [1, 1, C]: the non-reference token
        step = PastInputsStep(past, past_length, backbone.global_rope(x))
        output = backbone.run_alternating(x, (grid_h, grid_w), camera, step)
        return _head_inputs(output, grid_h, grid_w)


class CameraHeadGraph(nn.Module):
    """``camera_tokens`` [F, 2C] -> ``pose_enc`` [F, 9]: t, quaternion xyzw (unnormalised),
    fov_h, fov_w of the camera-to-world pose (``models/da3/camera.py``)."""

    def __init__(self, model: DepthAnything3) -> None:
        super().__init__()
        self.model = model

    def forward(self, camera_tokens: torch.Tensor) -> torch.Tensor:
        return cast(torch.Tensor, self.model.cam_dec(camera_tokens))


class DepthHeadGraph(nn.Module):
    """``features.{l}`` [F, h, w, 2C] (four levels) -> ``depth`` [F, H, W] (camera z, > 0) and
    ``depth_conf`` [F, H, W] (>= 1), H = 14h and W = 14w."""

    def __init__(self, model: DepthAnything3) -> None:
        super().__init__()
        self.model = model

    def forward(
        self, level0: torch.Tensor, level1: torch.Tensor, level2: torch.Tensor, level3: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        # four named arguments, not *features: torch.export matches dynamic shapes per argument
        features = (level0, level1, level2, level3)
        frames, grid_h, grid_w, _ = level0.shape
        patch = self.model.config.patch_size
        tokens = [feature.reshape(frames, grid_h * grid_w, -1) for feature in features]
        maps = self.model.head.forward_views(
            tokens, (grid_h * patch, grid_w * patch), with_rays=False
        )
        return maps.depth, maps.depth_conf

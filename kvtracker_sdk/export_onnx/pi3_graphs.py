"""Pi3 cut into exportable graphs: thin ``nn.Module`` views over one loaded ``Pi3``.

Each module's ``forward`` is the computation of one ONNX graph (names and shapes in
``backends/onnx_manifest.py``), written so that ``torch.export`` sees no data-dependent shape:

- the patch grid (h, w) travels in tensor shapes (``patch_tokens`` [F, h, w, dim],
  ``hidden_patches`` [F, h, w, 2*dim]), and RoPE tables are computed from it, so every graph
  keeps H and W dynamic;
- the tracking decoder attends over ``cat(past[:, :, :past_length], own)``
  (``past_attention.attend_past``); its past inputs may be whole ``KVCache`` buffers (cached
  tokens then scratch), passed without a copy;
- the camera head stops before the SVD: it returns the raw 9 rotation numbers and the
  translation, and ``backends/onnx_families.py`` finishes the pose in numpy.

The modules hold no weights of their own: they run the ``Pi3``'s submodules, so the exported
weights are the model's (and the weights fingerprint is the checkpoint's).
"""

from __future__ import annotations

from typing import cast

import torch
from torch import nn

from kvtracker_sdk.export_onnx.past_attention import attend_past
from kvtracker_sdk.models.layers.block import Block
from kvtracker_sdk.models.layers.rope2d import RopeTable, grid_positions, rope_table
from kvtracker_sdk.models.pi3 import Pi3

__all__ = [
    "CameraHeadGraph",
    "ConfHeadGraph",
    "DecoderMapGraph",
    "DecoderTrackGraph",
    "EncoderGraph",
    "PointsHeadGraph",
]


def _grid_rope(model: Pi3, grid_h: int, grid_w: int, head_dim: int, device: torch.device) -> RopeTable:
    """RoPE2D table of one frame's decoder tokens (registers, then the h x w patches)."""
    positions = grid_positions(
        grid_h, grid_w, num_prefix_tokens=model.num_register_tokens, device=device
    )
    return rope_table(positions, head_dim, base=model.config.decoder.rope_base)


def _decoder_tokens(model: Pi3, patch_tokens: torch.Tensor) -> tuple[torch.Tensor, RopeTable]:
    """[F, h, w, dim] -> decoder tokens [F, R + h*w, dim] (registers first) and their RoPE."""
    frames, grid_h, grid_w, dim = patch_tokens.shape
    registers = model.register_token.reshape(1, model.num_register_tokens, dim)
    tokens = torch.cat(
        (registers.expand(frames, -1, -1), patch_tokens.reshape(frames, grid_h * grid_w, dim)),
        dim=1,
    )
    rope = _grid_rope(model, grid_h, grid_w, model.decoder.head_dim, patch_tokens.device)
    return tokens, rope


def _split_hidden(
    model: Pi3, hidden: torch.Tensor, grid_h: int, grid_w: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """[F, R + h*w, C] -> registers [F, R, C] and patches [F, h, w, C]."""
    registers = model.num_register_tokens
    frames, channels = hidden.shape[0], hidden.shape[-1]
    return hidden[:, :registers], hidden[:, registers:].reshape(frames, grid_h, grid_w, channels)


class EncoderGraph(nn.Module):
    """``images`` [F, 3, H, W] RGB in [0, 1] -> ``patch_tokens`` [F, H/p, W/p, dim]."""

    def __init__(self, model: Pi3) -> None:
        super().__init__()
        self.model = model

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        model, patch = self.model, self.model.config.patch_size
        frames, _, height, width = images.shape
        normalised = (images - model.image_mean) / model.image_std
        patches = model.encoder(normalised)  # [F, h*w, dim]
        return patches.reshape(frames, height // patch, width // patch, -1)


class DecoderMapGraph(nn.Module):
    """Full attention over N keyframes; returns the hidden state and every global layer's K/V.

    ``patch_tokens`` [N, h, w, dim] -> ``hidden_registers`` [N, R, 2*dim], ``hidden_patches``
    [N, h, w, 2*dim], then per cached layer ``present.{i}.key`` and ``.value`` [1, heads, N*T,
    head_dim] (K after k_norm and RoPE; tokens keyframe-major, T = R + h*w).
    """

    def __init__(self, model: Pi3) -> None:
        super().__init__()
        self.model = model

    def forward(self, patch_tokens: torch.Tensor) -> tuple[torch.Tensor, ...]:
        _, grid_h, grid_w, _ = patch_tokens.shape
        tokens, rope = _decoder_tokens(self.model, patch_tokens)
        hidden, keys, values = self.model.decoder.forward_map(tokens.unsqueeze(0), rope)
        kv = [tensor for pair in zip(keys, values, strict=True) for tensor in pair]
        return (*_split_hidden(self.model, hidden[0], grid_h, grid_w), *kv)


class DecoderTrackGraph(nn.Module):
    """One query frame attending over a cache in every global layer.

    ``patch_tokens`` [1, h, w, dim], ``past_length`` int64 [] (cached tokens), ``past`` = per
    cached layer (key, value) [1, heads, capacity >= past_length, head_dim], flattened as key 0,
    value 0, key 1, ... -> ``hidden_registers`` [1, R, 2*dim], ``hidden_patches`` [1, h, w, 2*dim].
    """

    def __init__(self, model: Pi3) -> None:
        super().__init__()
        self.model = model

    def forward(
        self, patch_tokens: torch.Tensor, past_length: torch.Tensor, past: tuple[torch.Tensor, ...]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        _, grid_h, grid_w, _ = patch_tokens.shape
        tokens, rope = _decoder_tokens(self.model, patch_tokens)
        decoder = self.model.decoder
        cached_layer = {block: layer for layer, block in enumerate(decoder.global_block_indices)}
        x = tokens
        outputs = []  # the outputs of the last two blocks (the heads read their concatenation)
        for index, block in enumerate(decoder):
            if index in cached_layer:  # global attention over the cache and the frame itself
                layer = cached_layer[index]
                past_key, past_value = past[2 * layer], past[2 * layer + 1]
                x = attend_past(cast(Block, block), x, rope, past_key, past_value, past_length)
            else:  # attention within the frame
                x = block(x, rope=rope)
            if index >= len(decoder) - 2:
                outputs.append(x)
        return _split_hidden(self.model, torch.cat(outputs, dim=-1), grid_h, grid_w)


class _HeadGraph(nn.Module):
    """Base of the head graphs: (``hidden_registers``, ``hidden_patches``) -> head tokens."""

    def __init__(self, model: Pi3) -> None:
        super().__init__()
        self.model = model

    def _patch_tokens(
        self, decoder: nn.Module, hidden_registers: torch.Tensor, hidden_patches: torch.Tensor
    ) -> torch.Tensor:
        """Run a head decoder over [F, R + h*w, 2*dim]; its patch tokens [F, h*w, out_dim]."""
        model = self.model
        frames, grid_h, grid_w, channels = hidden_patches.shape
        hidden = torch.cat(
            (hidden_registers, hidden_patches.reshape(frames, grid_h * grid_w, channels)), dim=1
        )
        heads = model.config.heads
        rope = _grid_rope(
            model, grid_h, grid_w, heads.embed_dim // heads.num_heads, hidden.device
        )
        return decoder(hidden, rope)[:, model.num_register_tokens :]


class CameraHeadGraph(_HeadGraph):
    """-> ``rotation_raw`` [F, 9] (row-major 3x3, before row normalisation and SVD), ``translation`` [F, 3].

    The pose is camera-to-world once ``camera_poses`` projects the 3x3 onto SO(3).
    """

    def forward(
        self, hidden_registers: torch.Tensor, hidden_patches: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        tokens = self._patch_tokens(self.model.camera_decoder, hidden_registers, hidden_patches)
        head = self.model.camera_head
        for block in head.res_conv:
            tokens = block(tokens)
        pooled = head.more_mlps(tokens.mean(dim=1))  # mean over the patch tokens: [F, dim]
        return head.fc_rot(pooled), head.fc_t(pooled)


class ConfHeadGraph(_HeadGraph):
    """-> ``conf_logits`` [F, H, W] (sigmoid gives the confidence in [0, 1])."""

    def forward(self, hidden_registers: torch.Tensor, hidden_patches: torch.Tensor) -> torch.Tensor:
        _, grid_h, grid_w, _ = hidden_patches.shape
        tokens = self._patch_tokens(self.model.conf_decoder, hidden_registers, hidden_patches)
        return self.model.conf_head(tokens, grid_h, grid_w)[..., 0]


class PointsHeadGraph(_HeadGraph):
    """-> ``local_points`` [F, H, W, 3]: camera frame, OpenCV axes, z = exp(d) > 0."""

    def forward(self, hidden_registers: torch.Tensor, hidden_patches: torch.Tensor) -> torch.Tensor:
        _, grid_h, grid_w, _ = hidden_patches.shape
        tokens = self._patch_tokens(self.model.point_decoder, hidden_registers, hidden_patches)
        raw = self.model.point_head(tokens, grid_h, grid_w)  # [F, H, W, 3]: (u, v, d)
        xy, log_depth = raw.split([2, 1], dim=-1)
        depth = torch.exp(log_depth)
        return torch.cat((xy * depth, depth), dim=-1)

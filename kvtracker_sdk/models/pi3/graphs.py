"""Pi3 cut into exportable graphs: thin ``nn.Module`` views over one loaded ``Pi3``.

Each module's ``forward`` is the computation of one graph (signatures in ``graph_specs.py``) and
runs the model's own stages (``Pi3.encode``, ``decoder_tokens``, ``grid_rope``, ``Pi3Decoder.run``
with a global step from ``models/layers/alternating.py``, ``head_tokens``, ``CameraHead.raw``,
``local_points``), so there is one implementation of the network. Written so that
``torch.export`` sees no data-dependent shape:

- the patch grid (h, w) travels in tensor shapes (``patch_tokens`` [F, h, w, dim],
  ``hidden_patches`` [F, h, w, 2*dim]), and RoPE tables are computed from it, so every graph
  keeps H and W dynamic;
- the tracking decoder's global step is ``PastInputsStep``: it attends over
  ``cat(past[:, :, :past_length], own)``; its past inputs may be whole ``KVCache`` buffers
  (cached tokens then scratch), passed without a copy;
- the camera head stops before the SVD: it returns the raw 9 rotation numbers and the
  translation, and ``conventions.camera_poses`` finishes the pose in float64 numpy.

The modules hold no weights of their own, so the exported weights are the model's (and the
weights fingerprint is the checkpoint's).
"""

from __future__ import annotations

import torch
from torch import nn

from kvtracker_sdk.models.layers.alternating import PastInputsStep
from kvtracker_sdk.models.layers.rope2d import RopeTable
from kvtracker_sdk.models.pi3.model import Pi3

__all__ = [
    "CameraHeadGraph",
    "ConfHeadGraph",
    "DecoderMapGraph",
    "DecoderTrackGraph",
    "EncoderGraph",
    "PointsHeadGraph",
]


class _Pi3Graph(nn.Module):
    def __init__(self, model: Pi3) -> None:
        super().__init__()
        self.model = model

    def _decoder_input(self, patch_tokens: torch.Tensor) -> tuple[torch.Tensor, RopeTable]:
        """[F, h, w, dim] -> decoder tokens [1, F, R + h*w, dim] (one sequence) and one frame's
        RoPE table."""
        frames, grid_h, grid_w, dim = patch_tokens.shape
        model = self.model
        tokens = model.decoder_tokens(patch_tokens.reshape(frames, grid_h * grid_w, dim))
        rope = model.grid_rope(grid_h, grid_w, model.decoder.head_dim, device=tokens.device)
        return tokens.unsqueeze(0), rope

    def _split_hidden(
        self, hidden: torch.Tensor, grid_h: int, grid_w: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """[F, R + h*w, C] -> registers [F, R, C] and patches [F, h, w, C]."""
        registers = self.model.num_register_tokens
        frames, channels = hidden.shape[0], hidden.shape[-1]
        return hidden[:, :registers], hidden[:, registers:].reshape(frames, grid_h, grid_w, channels)


class EncoderGraph(_Pi3Graph):
    """``images`` [F, 3, H, W] RGB in [0, 1] -> ``patch_tokens`` [F, H/p, W/p, dim]."""

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        frames, _, height, width = images.shape
        patch = self.model.config.patch_size
        return self.model.encode(images).reshape(frames, height // patch, width // patch, -1)


class DecoderMapGraph(_Pi3Graph):
    """Full attention over N keyframes; returns the hidden state and every global layer's K/V.

    ``patch_tokens`` [N, h, w, dim] -> ``hidden_registers`` [N, R, 2*dim], ``hidden_patches``
    [N, h, w, 2*dim], then per cached layer ``present.{i}.key`` and ``.value`` [1, heads, N*T,
    head_dim] (K after k_norm and RoPE; tokens keyframe-major, T = R + h*w).
    """

    def forward(self, patch_tokens: torch.Tensor) -> tuple[torch.Tensor, ...]:
        _, grid_h, grid_w, _ = patch_tokens.shape
        tokens, rope = self._decoder_input(patch_tokens)
        hidden, keys, values = self.model.decoder.forward_map(tokens, rope)
        kv = [tensor for pair in zip(keys, values, strict=True) for tensor in pair]
        return (*self._split_hidden(hidden[0], grid_h, grid_w), *kv)


class DecoderTrackGraph(_Pi3Graph):
    """One query frame attending over a cache in every global layer.

    ``patch_tokens`` [1, h, w, dim], ``past_length`` int64 [] (cached tokens), ``past`` = per
    cached layer (key, value) [1, heads, capacity >= past_length, head_dim], flattened as key 0,
    value 0, key 1, ... -> ``hidden_registers`` [1, R, 2*dim], ``hidden_patches`` [1, h, w, 2*dim].
    """

    def forward(
        self, patch_tokens: torch.Tensor, past_length: torch.Tensor, past: tuple[torch.Tensor, ...]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        _, grid_h, grid_w, _ = patch_tokens.shape
        tokens, rope = self._decoder_input(patch_tokens)
        hidden = self.model.decoder.run(tokens, rope, PastInputsStep(past, past_length, rope))
        return self._split_hidden(hidden[0], grid_h, grid_w)


class _HeadGraph(_Pi3Graph):
    """Base of the head graphs: (``hidden_registers``, ``hidden_patches``) -> head tokens."""

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
        rope = model.grid_rope(
            grid_h, grid_w, heads.embed_dim // heads.num_heads, device=hidden.device
        )
        return model.head_tokens(decoder, hidden, rope)


class CameraHeadGraph(_HeadGraph):
    """-> ``rotation_raw`` [F, 9] (row-major 3x3, before row normalisation and SVD), ``translation`` [F, 3].

    The pose is camera-to-world once ``conventions.camera_poses`` projects the 3x3 onto SO(3).
    """

    def forward(
        self, hidden_registers: torch.Tensor, hidden_patches: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        tokens = self._patch_tokens(self.model.camera_decoder, hidden_registers, hidden_patches)
        return self.model.camera_head.raw(tokens)


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
        return self.model.local_points(self.model.point_head(tokens, grid_h, grid_w))

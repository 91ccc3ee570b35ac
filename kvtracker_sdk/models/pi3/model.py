"""``Pi3``: the π³ multi-view geometry network, with the mapping/tracking split of KV-Tracker.

Input images are RGB in [0, 1]; the model subtracts the ImageNet mean and divides by the std
itself (buffers ``image_mean`` / ``image_std``). H and W must be multiples of 14. Outputs follow
the official code: ``camera_poses`` camera-to-world [B, N, 4, 4] and points in OpenCV axes, in a
world frame and scale the pass picks itself (frame 0 is not the identity).

Passes (all under ``torch.no_grad()`` in inference code):

- ``model(imgs [B, N, 3, H, W])`` -> ``Pi3Output``: the official forward. With
  ``global_attn_mask`` (bool [N*T, N*T]) the global blocks attend under that mask — with
  ``keyframe_query_mask`` this is the reference for the tracking pass.
- ``model.forward_map(imgs [B, N, 3, H, W])`` -> ``Pi3MapOutput``: the forward plus, for every
  global block, K (after k_norm and RoPE) and V as they enter the attention, [B, heads, N*T,
  head_dim] each, register tokens included (tokens frame-major, T per frame).
- ``model.forward_track(imgs [F, 3, H, W], cache)`` -> ``Pi3Output`` with leading dims [F, 1]: F
  independent query frames, each attending in every global block to all cached tokens plus its
  own. ``cache`` is anything with ``length``, ``ensure_capacity(tokens)`` and ``buffers(layer)``
  (``kvtracker_sdk.cache.KVCache``); its cached part is only read.

``heads`` (``HeadSet``) selects the outputs: CAMERA computes only ``camera_poses`` (the fastest
step), CONFIDENCE adds ``conf``, ALL adds ``local_points`` and ``points``.

Precision: ``set_precision(torch.bfloat16)`` runs the official bf16 recipe (``torch.autocast``
over the encoder, decoder and head decoders; see ``models/layers/precision.py``) with the weights of
their Linear/conv layers stored in bf16 once: matrix products and the K/V cache in bf16, the
residual stream, norms, LayerScales and tokens in fp32, RoPE angles rounded to bf16 as in the
official code. ``point_head``, ``conf_head`` and ``camera_head`` stay fp32 with autocast off.
The exported graphs (``graphs.py``) are fp32 and run the same stages without autocast.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import torch
from torch import nn

from kvtracker_sdk.errors import ImageShapeError
from kvtracker_sdk.models.layers.attention import CacheBuffers
from kvtracker_sdk.models.layers.patch_embed import IMAGENET_MEAN, IMAGENET_STD
from kvtracker_sdk.models.layers.precision import cast_matmul_weights, matmul_dtype, trunk_autocast
from kvtracker_sdk.models.layers.rope2d import RopeTable, grid_positions, rope_table
from kvtracker_sdk.models.layers.vit_encoder import DinoViT
from kvtracker_sdk.models.pi3.config import Pi3Config
from kvtracker_sdk.models.pi3.decoder import Pi3Decoder
from kvtracker_sdk.models.pi3.heads import (
    CameraHead,
    HeadDecoder,
    PixelShuffleHead,
    project_pose_rotations,
)
from kvtracker_sdk.types import HeadSet

__all__ = ["Pi3", "Pi3MapOutput", "Pi3Output"]

_FP32_HEADS = ("point_head", "conf_head", "camera_head")


@dataclass(frozen=True)
class Pi3Output:
    """Outputs of a pass over [B, N] frames (float32). Unrequested heads are None."""

    camera_poses: torch.Tensor  # [B, N, 4, 4] camera-to-world, OpenCV axes
    conf: torch.Tensor | None = None  # [B, N, H, W, 1] confidence logits (sigmoid -> [0, 1])
    local_points: torch.Tensor | None = None  # [B, N, H, W, 3] camera frame, z = exp(d) > 0
    points: torch.Tensor | None = None  # [B, N, H, W, 3] world frame: camera_poses @ local_points


@dataclass(frozen=True)
class Pi3MapOutput:
    """A mapping pass: its outputs and the K/V of every global block (the cache content)."""

    output: Pi3Output
    keys: list[torch.Tensor]  # per global block [B, heads, N*T, head_dim], after k_norm + RoPE
    values: list[torch.Tensor]  # per global block [B, heads, N*T, head_dim]
    tokens_per_frame: int  # T = decoder registers + (H/14)*(W/14)


class Pi3(nn.Module):
    """π³ with module names equal to the official checkpoint's (``model.safetensors`` loads strictly)."""

    image_mean: torch.Tensor  # [1, 3, 1, 1] buffer, ImageNet mean
    image_std: torch.Tensor  # [1, 3, 1, 1] buffer, ImageNet std

    def __init__(self, config: Pi3Config | None = None) -> None:
        super().__init__()
        self.config = config = config or Pi3Config.large()
        enc, dec, heads = config.encoder, config.decoder, config.heads
        self.encoder = DinoViT(
            embed_dim=enc.embed_dim,
            depth=enc.depth,
            num_heads=enc.num_heads,
            patch_size=config.patch_size,
            mlp_ratio=enc.mlp_ratio,
            pos_embed_grid=enc.pos_embed_grid,
            num_register_tokens=enc.num_register_tokens,
            interpolate_antialias=True,
            layerscale_init=1.0,
        )
        self.decoder = Pi3Decoder(dec)
        self.register_token = nn.Parameter(
            torch.randn(1, 1, dec.num_register_tokens, dec.embed_dim) * 1e-6
        )

        def head_decoder(out_dim: int) -> HeadDecoder:
            return HeadDecoder(
                2 * dec.embed_dim,
                out_dim,
                embed_dim=heads.embed_dim,
                depth=heads.depth,
                num_heads=heads.num_heads,
                mlp_ratio=heads.mlp_ratio,
            )

        self.point_decoder = head_decoder(heads.point_out_dim)
        self.point_head = PixelShuffleHead(heads.point_out_dim, 3, config.patch_size)
        self.conf_decoder = head_decoder(heads.point_out_dim)
        self.conf_head = PixelShuffleHead(heads.point_out_dim, 1, config.patch_size)
        self.camera_decoder = head_decoder(heads.camera_out_dim)
        self.camera_head = CameraHead(heads.camera_out_dim)
        self.register_buffer("image_mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1))
        self.register_buffer("image_std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1))

    # ------------------------------------------------------------------ properties
    @property
    def compute_dtype(self) -> torch.dtype:
        """dtype of the trunk's matrix products (the KV cache's dtype); the final heads stay fp32."""
        return self.encoder.patch_embed.proj.weight.dtype

    @property
    def num_register_tokens(self) -> int:
        return self.config.decoder.num_register_tokens

    def tokens_per_frame(self, height: int, width: int) -> int:
        """Decoder tokens per frame: registers + (H/14)*(W/14)."""
        patch = self.config.patch_size
        return self.num_register_tokens + (height // patch) * (width // patch)

    def set_precision(self, dtype: torch.dtype) -> Pi3:
        """Matrix products of the trunk (encoder, decoder, head decoders) in ``dtype``.

        Their Linear/conv weights are cast to ``dtype`` and the passes run the trunk under
        ``torch.autocast(dtype)``; every other parameter, and the final heads, stay fp32.
        """
        self.to(torch.float32)
        if dtype != torch.float32:
            for name, module in self.named_children():
                if name not in _FP32_HEADS:
                    cast_matmul_weights(module, dtype)
        return self

    # ------------------------------------------------------------------ passes
    def forward(
        self,
        imgs: torch.Tensor,
        *,
        heads: HeadSet = HeadSet.ALL,
        global_attn_mask: torch.Tensor | None = None,
    ) -> Pi3Output:
        """Official forward on ``imgs`` [B, N, 3, H, W] in [0, 1]; see the module docstring."""
        with self._trunk_precision(imgs):
            tokens, rope = self._encode(imgs)
            hidden = self.decoder(tokens, rope, global_attn_mask=global_attn_mask)
            return self._heads(hidden, (imgs.shape[-2], imgs.shape[-1]), heads)

    def forward_map(self, imgs: torch.Tensor, *, heads: HeadSet = HeadSet.ALL) -> Pi3MapOutput:
        """Forward on keyframes [B, N, 3, H, W] that also returns every global block's K/V."""
        with self._trunk_precision(imgs):
            tokens, rope = self._encode(imgs)
            hidden, keys, values = self.decoder.forward_map(tokens, rope)
            output = self._heads(hidden, (imgs.shape[-2], imgs.shape[-1]), heads)
        return Pi3MapOutput(output, keys, values, tokens_per_frame=tokens.shape[2])

    def forward_track(
        self, imgs: torch.Tensor, cache: CacheBuffers, *, heads: HeadSet = HeadSet.CAMERA
    ) -> Pi3Output:
        """Track F independent frames [F, 3, H, W] against ``cache``; outputs have dims [F, 1, ...]."""
        if imgs.dim() != 4:
            raise ImageShapeError(
                f"tracking expects frames [F, 3, H, W], got shape {tuple(imgs.shape)}"
            )
        with self._trunk_precision(imgs):
            tokens, rope = self._encode(imgs.unsqueeze(0))  # one sequence of F frames
            hidden = self.decoder.forward_track(tokens, rope, cache)
            # [1, F, T, 2*dim] -> [F, 1, T, 2*dim]: the frames are independent sequences
            return self._heads(hidden.transpose(0, 1), (imgs.shape[-2], imgs.shape[-1]), heads)

    # ------------------------------------------------------------------ stages
    # (public: the exported graphs, ``models/pi3/graphs.py``, are made of them)
    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """Frames [F, 3, H, W] RGB in [0, 1] -> patch tokens [F, h*w, dim], fp32 (the residual
        stream's dtype; under the trunk's autocast the patch conv runs in bf16)."""
        normalised = (images.float() - self.image_mean) / self.image_std
        return self.encoder(normalised)

    def decoder_tokens(self, patches: torch.Tensor) -> torch.Tensor:
        """Patch tokens [F, h*w, dim] -> decoder tokens [F, R + h*w, dim] (registers first)."""
        registers = self.register_token.reshape(1, self.num_register_tokens, -1)
        return torch.cat((registers.expand(patches.shape[0], -1, -1), patches), dim=1)

    def grid_rope(
        self,
        grid_h: int,
        grid_w: int,
        head_dim: int,
        *,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> RopeTable:
        """RoPE2D table [R + h*w, head_dim] of one frame's tokens (registers, then the h x w
        patches; angles rounded to ``dtype``)."""
        positions = grid_positions(
            grid_h, grid_w, num_prefix_tokens=self.num_register_tokens, device=device
        )
        return rope_table(positions, head_dim, base=self.config.decoder.rope_base, dtype=dtype)

    def head_tokens(self, decoder: nn.Module, hidden: torch.Tensor, rope: RopeTable) -> torch.Tensor:
        """A head decoder over the decoder output [F, R + h*w, 2*dim] -> its patch tokens
        [F, h*w, out_dim] (the heads read patch tokens only)."""
        return decoder(hidden, rope)[:, self.num_register_tokens :]

    @staticmethod
    def local_points(raw: torch.Tensor) -> torch.Tensor:
        """The point head's (u, v, d) [..., 3] -> camera-frame points, z = exp(d) > 0."""
        xy, log_depth = raw.split([2, 1], dim=-1)
        depth = torch.exp(log_depth)
        return torch.cat((xy * depth, depth), dim=-1)

    def _trunk_precision(self, imgs: torch.Tensor) -> contextlib.AbstractContextManager[object]:
        """Autocast to the compute dtype around a pass (none in fp32); the final heads opt out."""
        return trunk_autocast(self.compute_dtype, imgs.device)

    def _encode(self, imgs: torch.Tensor) -> tuple[torch.Tensor, RopeTable]:
        """[B, N, 3, H, W] in [0, 1] -> decoder tokens [B, N, T, dim] and one frame's RoPE table."""
        if imgs.dim() != 5 or imgs.shape[2] != 3:
            raise ImageShapeError(f"expected images [B, N, 3, H, W], got shape {tuple(imgs.shape)}")
        batch, frames, _, height, width = imgs.shape
        tokens = self.decoder_tokens(self.encode(imgs.reshape(batch * frames, 3, height, width)))
        patch = self.config.patch_size
        rope = self.grid_rope(
            height // patch,
            width // patch,
            self.decoder.head_dim,
            dtype=matmul_dtype(tokens),
            device=imgs.device,
        )
        return tokens.reshape(batch, frames, tokens.shape[1], -1), rope

    def _heads(self, hidden: torch.Tensor, image_size: tuple[int, int], heads: HeadSet) -> Pi3Output:
        """Decoder output [B, N, T, 2*dim] -> per-frame outputs (float32)."""
        batch, frames, length, _ = hidden.shape
        height, width = image_size
        grid_h, grid_w = height // self.config.patch_size, width // self.config.patch_size
        hidden = hidden.reshape(batch * frames, length, -1)
        head_dim = self.config.heads.embed_dim // self.config.heads.num_heads
        rope = self.grid_rope(
            grid_h, grid_w, head_dim, dtype=matmul_dtype(hidden), device=hidden.device
        )

        camera_tokens = self.head_tokens(self.camera_decoder, hidden, rope)
        conf_tokens = None
        if heads is not HeadSet.CAMERA:
            conf_tokens = self.head_tokens(self.conf_decoder, hidden, rope)
        point_tokens = None
        if heads is HeadSet.ALL:
            point_tokens = self.head_tokens(self.point_decoder, hidden, rope)

        conf = local_points = points = None
        # The final heads run in fp32 even under a caller's autocast (SVD/det have no bf16 kernels).
        with torch.autocast(device_type=hidden.device.type, enabled=False):
            poses = self.camera_head(camera_tokens.float()).reshape(batch, frames, 4, 4)
            if conf_tokens is not None:
                conf = self.conf_head(conf_tokens.float(), grid_h, grid_w)
                conf = conf.reshape(batch, frames, height, width, 1)
            if point_tokens is not None:
                raw = self.point_head(point_tokens.float(), grid_h, grid_w)
                local_points = self.local_points(raw.reshape(batch, frames, height, width, 3))
                points = _world_points(poses, local_points)
        return Pi3Output(camera_poses=poses, conf=conf, local_points=local_points, points=points)

    @staticmethod
    def finish_captured_track(output: Pi3Output) -> Pi3Output:
        """``forward_track``'s output as replayed from a CUDA graph -> the eager output: the
        camera head leaves the SVD projection out of a graph (``CameraHead.forward``), so it and
        the world points that depend on it are computed here."""
        with torch.autocast(device_type=output.camera_poses.device.type, enabled=False):
            poses = project_pose_rotations(output.camera_poses)
            points = None
            if output.local_points is not None:
                points = _world_points(poses, output.local_points)
        return Pi3Output(
            camera_poses=poses, conf=output.conf, local_points=output.local_points, points=points
        )


def _world_points(poses: torch.Tensor, local_points: torch.Tensor) -> torch.Tensor:
    """Camera-frame points [B, N, H, W, 3] -> world points under poses [B, N, 4, 4]."""
    rotation, translation = poses[..., :3, :3], poses[..., :3, 3]
    return torch.einsum("bnij,bnhwj->bnhwi", rotation, local_points) + translation[:, :, None, None]

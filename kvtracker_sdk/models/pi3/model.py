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

Precision: ``set_precision(torch.bfloat16)`` casts the encoder, decoder and head decoders to bf16
(RoPE angles rounded to bf16 as in the official code) and keeps ``point_head``, ``conf_head`` and
``camera_head`` in fp32, like the official bf16 inference path.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from kvtracker_sdk.errors import ImageShapeError
from kvtracker_sdk.models.layers.attention import CacheBuffers
from kvtracker_sdk.models.layers.rope2d import RopeTable, grid_positions, rope_table
from kvtracker_sdk.models.layers.vit_encoder import DinoViT
from kvtracker_sdk.models.pi3.config import Pi3Config
from kvtracker_sdk.models.pi3.decoder import Pi3Decoder
from kvtracker_sdk.models.pi3.heads import CameraHead, HeadDecoder, PixelShuffleHead
from kvtracker_sdk.types import HeadSet

__all__ = ["Pi3", "Pi3MapOutput", "Pi3Output"]

_FP32_HEADS = ("point_head", "conf_head", "camera_head")
_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)


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
        self.register_buffer("image_mean", torch.tensor(_IMAGENET_MEAN).view(1, 3, 1, 1))
        self.register_buffer("image_std", torch.tensor(_IMAGENET_STD).view(1, 3, 1, 1))

    # ------------------------------------------------------------------ properties
    @property
    def compute_dtype(self) -> torch.dtype:
        """dtype of the encoder/decoder (the KV cache's dtype); the final heads stay fp32."""
        return self.register_token.dtype

    @property
    def num_register_tokens(self) -> int:
        return self.config.decoder.num_register_tokens

    def tokens_per_frame(self, height: int, width: int) -> int:
        """Decoder tokens per frame: registers + (H/14)*(W/14)."""
        patch = self.config.patch_size
        return self.num_register_tokens + (height // patch) * (width // patch)

    def set_precision(self, dtype: torch.dtype) -> Pi3:
        """Cast the trunk (encoder, decoder, head decoders) to ``dtype``; final heads stay fp32."""
        for name, module in self.named_children():
            module.to(torch.float32 if name in _FP32_HEADS else dtype)
        self.register_token.data = self.register_token.data.to(dtype)
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
        tokens, positions = self._encode(imgs)
        rope = self._rope(positions, self.decoder.head_dim, tokens.dtype)
        hidden = self.decoder(tokens, rope, global_attn_mask=global_attn_mask)
        return self._heads(hidden, positions, (imgs.shape[-2], imgs.shape[-1]), heads)

    def forward_map(self, imgs: torch.Tensor, *, heads: HeadSet = HeadSet.ALL) -> Pi3MapOutput:
        """Forward on keyframes [B, N, 3, H, W] that also returns every global block's K/V."""
        tokens, positions = self._encode(imgs)
        rope = self._rope(positions, self.decoder.head_dim, tokens.dtype)
        hidden, keys, values = self.decoder.forward_map(tokens, rope)
        output = self._heads(hidden, positions, (imgs.shape[-2], imgs.shape[-1]), heads)
        return Pi3MapOutput(output, keys, values, tokens_per_frame=tokens.shape[2])

    def forward_track(
        self, imgs: torch.Tensor, cache: CacheBuffers, *, heads: HeadSet = HeadSet.CAMERA
    ) -> Pi3Output:
        """Track F independent frames [F, 3, H, W] against ``cache``; outputs have dims [F, 1, ...]."""
        if imgs.dim() != 4:
            raise ImageShapeError(
                f"tracking expects frames [F, 3, H, W], got shape {tuple(imgs.shape)}"
            )
        tokens, positions = self._encode(imgs.unsqueeze(0))  # one sequence of F frames
        rope = self._rope(positions, self.decoder.head_dim, tokens.dtype)
        hidden = self.decoder.forward_track(tokens, rope, cache)
        # [1, F, T, 2*dim] -> [F, 1, T, 2*dim]: the frames are independent sequences
        return self._heads(
            hidden.transpose(0, 1), positions, (imgs.shape[-2], imgs.shape[-1]), heads
        )

    # ------------------------------------------------------------------ stages
    def _encode(self, imgs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """[B, N, 3, H, W] in [0, 1] -> decoder tokens [B, N, T, dim], positions [T, 2]."""
        if imgs.dim() != 5 or imgs.shape[2] != 3:
            raise ImageShapeError(f"expected images [B, N, 3, H, W], got shape {tuple(imgs.shape)}")
        batch, frames, _, height, width = imgs.shape
        normalised = (
            imgs.reshape(batch * frames, 3, height, width).float() - self.image_mean
        ) / self.image_std
        patches = self.encoder(normalised.to(self.compute_dtype))  # [B*N, h*w, dim]
        registers = self.register_token.reshape(1, self.num_register_tokens, -1)
        tokens = torch.cat((registers.expand(batch * frames, -1, -1), patches), dim=1)
        patch = self.config.patch_size
        positions = grid_positions(
            height // patch,
            width // patch,
            num_prefix_tokens=self.num_register_tokens,
            device=imgs.device,
        )
        return tokens.reshape(batch, frames, tokens.shape[1], -1), positions

    def _rope(self, positions: torch.Tensor, head_dim: int, dtype: torch.dtype) -> RopeTable:
        """RoPE2D table of one frame's positions [T, 2] (angles rounded to ``dtype``)."""
        return rope_table(positions, head_dim, base=self.config.decoder.rope_base, dtype=dtype)

    def _heads(
        self,
        hidden: torch.Tensor,
        positions: torch.Tensor,
        image_size: tuple[int, int],
        heads: HeadSet,
    ) -> Pi3Output:
        """Decoder output [B, N, T, 2*dim] -> per-frame outputs (float32)."""
        batch, frames, length, _ = hidden.shape
        height, width = image_size
        grid_h, grid_w = height // self.config.patch_size, width // self.config.patch_size
        hidden = hidden.reshape(batch * frames, length, -1)
        head_dim = self.config.heads.embed_dim // self.config.heads.num_heads
        rope = self._rope(positions, head_dim, hidden.dtype)
        skip = self.num_register_tokens  # the heads read patch tokens only

        camera_tokens = self.camera_decoder(hidden, rope)[:, skip:]
        conf_tokens = None if heads is HeadSet.CAMERA else self.conf_decoder(hidden, rope)[:, skip:]
        point_tokens = self.point_decoder(hidden, rope)[:, skip:] if heads is HeadSet.ALL else None

        conf = local_points = points = None
        # The final heads run in fp32 even under a caller's autocast (SVD/det have no bf16 kernels).
        with torch.autocast(device_type=hidden.device.type, enabled=False):
            poses = self.camera_head(camera_tokens.float()).reshape(batch, frames, 4, 4)
            if conf_tokens is not None:
                conf = self.conf_head(conf_tokens.float(), grid_h, grid_w)
                conf = conf.reshape(batch, frames, height, width, 1)
            if point_tokens is not None:
                raw = self.point_head(point_tokens.float(), grid_h, grid_w)
                xy, log_depth = raw.reshape(batch, frames, height, width, 3).split([2, 1], dim=-1)
                depth = torch.exp(log_depth)
                local_points = torch.cat((xy * depth, depth), dim=-1)
                rotation, translation = poses[..., :3, :3], poses[..., :3, 3]
                points = (
                    torch.einsum("bnij,bnhwj->bnhwi", rotation, local_points)
                    + translation[:, :, None, None]
                )
        return Pi3Output(camera_poses=poses, conf=conf, local_points=local_points, points=points)

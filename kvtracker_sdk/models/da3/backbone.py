"""DA3's backbone: a DINOv2 ViT whose blocks alternate per-view and cross-view attention.

Tokens of one view (no registers): ``[cls | h*w patches]``, T = 1 + h*w, as in DINOv2 (pos-embed
grid resized with ``scale_factor=((h+0.1)/37, (w+0.1)/37)``, bicubic, no antialias). Then, for
block ``i`` over views [B, N, T, C]:

- ``i < alt_start``: plain DINOv2 block on each view (no qk-norm, no RoPE);
- ``i == alt_start``: token 0 of every view is overwritten by a camera token — the reference
  view's ``camera_token[:, 0]``, every other view's ``camera_token[:, 1]`` (or per-view tokens of
  the pose encoder);
- ``i >= alt_start``, even: per-view block with qk-norm and RoPE2D at (0, 0) for token 0 and
  (r+1, c+1) for the patch in row r, column c;
- ``i >= alt_start``, odd: **global** block over the sequence [B, N*T] (views in order) with RoPE
  at (0, 0) for token 0 and (1, 1) for every patch. These are the only places where views
  interact, and the layers a KV cache stores.

For each out layer l the heads read ``cat(last local output, output of l)`` [B, N, T, 2C]:
features are ``cat(local half, norm(global half))`` without token 0, and the camera decoder reads
token 0 of the last out layer, not normalised.

Three passes differ only in the camera tokens and the global blocks (see ``DA3Backbone``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import torch
from torch import nn

from kvtracker_sdk.errors import ImageShapeError
from kvtracker_sdk.models.da3.config import DA3Config
from kvtracker_sdk.models.da3.reference_view import ReferenceStrategy, select_reference_view
from kvtracker_sdk.models.layers.alternating import (
    CacheTrackingStep,
    FullStep,
    GlobalStep,
    KVRecordingStep,
    run_alternating,
)
from kvtracker_sdk.models.layers.attention import CacheBuffers
from kvtracker_sdk.models.layers.cache_layout import CacheLayout
from kvtracker_sdk.models.layers.precision import matmul_dtype
from kvtracker_sdk.models.layers.rope2d import RopeTable, grid_positions, rope_table
from kvtracker_sdk.models.layers.vit_encoder import DinoViT

__all__ = ["BackboneOutput", "DA3Backbone", "DA3ViT", "global_positions"]

# input of block alt_start - 1 [B, N, T, C] -> (camera tokens [B, N, C], reference view [B] or None)
CameraChoice = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor | None]]


def global_positions(
    tokens_per_frame: int, *, device: torch.device | str | None = None
) -> torch.Tensor:
    """RoPE positions of one view in global blocks: [T, 2] int64, (0, 0) then (1, 1) for every patch."""
    positions = torch.ones(tokens_per_frame, 2, dtype=torch.long, device=device)
    positions[0] = 0
    return positions


@dataclass(frozen=True)
class BackboneOutput:
    """What the heads read, per view."""

    features: list[torch.Tensor]  # per out layer [B, N, h*w, 2C]: cat(local, norm(global)), patches
    camera_tokens: torch.Tensor  # [B, N, 2C]: token 0 of cat(local, global) at the last out layer
    reference_view: torch.Tensor | None  # [B] int64: the view given camera_token[:, 0]


class DA3ViT(DinoViT):
    """``backbone.pretrained``: DINOv2 ViT/14 plus ``camera_token`` [1, 2, C] (reference, other)."""

    def __init__(self, config: DA3Config) -> None:
        vit = config.backbone
        super().__init__(
            embed_dim=vit.embed_dim,
            depth=vit.depth,
            num_heads=vit.num_heads,
            patch_size=config.patch_size,
            mlp_ratio=vit.mlp_ratio,
            pos_embed_grid=vit.pos_embed_grid,
            interpolate_antialias=False,
            interpolate_offset=0.1,
            layerscale_init=1.0,
            qk_norm_start=vit.alt_start,
            final_norm_eps=1e-5,
            ffn=vit.ffn,
        )
        self.camera_token = nn.Parameter(torch.randn(1, 2, vit.embed_dim) * 0.02)


class DA3Backbone(nn.Module):
    """``backbone``: holds ``pretrained`` (the checkpoint's nesting) and runs the three passes.

    - ``forward``: all views together; reference view chosen by ``strategy`` (or camera tokens
      given by the pose encoder); optional ``global_attn_mask`` bool [N*T, N*T] (True = attend).
    - ``forward_map``: reference pinned to view 0; also returns every global block's K (after
      k_norm and RoPE) and V, [B, heads, N*T, head_dim] each, camera tokens included.
    - ``forward_track``: F independent query views, each with ``camera_token[:, 1]``, attending in
      every global block to a cache's tokens plus their own.
    """

    def __init__(self, config: DA3Config) -> None:
        super().__init__()
        self.config = config
        self.pretrained = DA3ViT(config)
        vit = config.backbone
        self.alt_start = vit.alt_start
        self.out_layers = vit.out_layers
        self.layout = CacheLayout(vit.global_block_indices, vit.num_heads, vit.head_dim)
        self.num_heads = vit.num_heads
        self.head_dim = vit.head_dim
        self.global_block_indices = vit.global_block_indices

    # ------------------------------------------------------------------ passes
    def forward(
        self,
        images: torch.Tensor,
        *,
        strategy: ReferenceStrategy = "saddle_balanced",
        camera_tokens: torch.Tensor | None = None,
        global_attn_mask: torch.Tensor | None = None,
    ) -> BackboneOutput:
        """Normalised images [B, N, 3, H, W] -> ``BackboneOutput`` (``camera_tokens`` [B, N, C]
        from the pose encoder replace the learned ones and skip reference selection)."""
        tokens, grid = self.embed_views(images)
        views = tokens.shape[1]

        def choose(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
            if camera_tokens is not None:
                return camera_tokens.to(x.dtype), None
            reference = select_reference_view(x[:, :, 0], strategy)
            return self.learned_camera_tokens(reference, views), reference

        rope = self.global_rope(tokens).repeat(views)
        return self._run(tokens, grid, choose, FullStep(rope, global_attn_mask))

    def forward_map(
        self, images: torch.Tensor
    ) -> tuple[BackboneOutput, list[torch.Tensor], list[torch.Tensor]]:
        """Keyframes [B, N, 3, H, W] with view 0 as reference -> (output, keys, values)."""
        tokens, grid = self.embed_views(images)
        batch, views = tokens.shape[:2]
        step = KVRecordingStep(self.global_rope(tokens).repeat(views))

        def choose(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
            reference = torch.zeros(batch, dtype=torch.long, device=x.device)  # keyframe 0
            return self.learned_camera_tokens(reference, views), reference

        return self._run(tokens, grid, choose, step), step.keys, step.values

    def forward_track(self, images: torch.Tensor, cache: CacheBuffers) -> BackboneOutput:
        """Query views [F, 3, H, W] against ``cache`` -> output with leading dims [1, F].

        Each view's global attention sees the cached tokens and its own T tokens (one SDPA call
        with a block mask when F > 1). The views' K/V go to the cache's scratch region; the
        cached part is only read.
        """
        if images.dim() != 4:
            raise ImageShapeError(
                f"tracking expects views [F, 3, H, W], got shape {tuple(images.shape)}"
            )
        tokens, grid = self.embed_views(images.unsqueeze(0))  # one sequence of F views
        views = tokens.shape[1]
        step = CacheTrackingStep(
            cache,
            self.layout,
            frames=views,
            tokens_per_frame=tokens.shape[2],
            rope=self.global_rope(tokens),
            dtype=matmul_dtype(tokens),  # the cache holds K/V in the matrix products' dtype
            device=tokens.device,
        )

        def choose(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
            return self.pretrained.camera_token[:, 1:].expand(1, views, -1), None

        return self._run(tokens, grid, choose, step)

    # ------------------------------------------------------------------ internals
    def embed_views(self, images: torch.Tensor) -> tuple[torch.Tensor, tuple[int, int]]:
        """[B, N, 3, H, W] -> tokens [B, N, T, C] (cls + patches, position-embedded), (h, w)."""
        if images.dim() != 5 or images.shape[2] != 3:
            raise ImageShapeError(
                f"expected images [B, N, 3, H, W], got shape {tuple(images.shape)}"
            )
        batch, views = images.shape[:2]
        patch = self.config.patch_size
        tokens = self.pretrained.prepare_tokens(images.flatten(0, 1))  # [B*N, T, C]
        return tokens.unflatten(0, (batch, views)), (
            images.shape[-2] // patch,
            images.shape[-1] // patch,
        )

    def learned_camera_tokens(self, reference: torch.Tensor, views: int) -> torch.Tensor:
        """[B, N, C]: ``camera_token[:, 0]`` for each sequence's reference view, else ``[:, 1]``."""
        is_reference = torch.arange(views, device=reference.device) == reference.unsqueeze(1)
        learned = self.pretrained.camera_token[0]  # [2, C]: reference, other
        return torch.where(is_reference.unsqueeze(-1), learned[0], learned[1])

    def _rope(self, positions: torch.Tensor, dtype: torch.dtype) -> RopeTable:
        return rope_table(
            positions, self.head_dim, base=self.config.backbone.rope_base, dtype=dtype
        )

    def global_rope(self, tokens: torch.Tensor) -> RopeTable:
        """One view's global-block table [T, head_dim] (repeat it per view for [N*T])."""
        positions = global_positions(tokens.shape[2], device=tokens.device)
        return self._rope(positions, matmul_dtype(tokens))

    def _run(
        self,
        tokens: torch.Tensor,
        grid: tuple[int, int],
        choose: CameraChoice,
        global_step: GlobalStep,
    ) -> BackboneOutput:
        x = tokens
        early: list[torch.Tensor] = []  # out layers before alt_start (no official config has one)
        for index in range(self.alt_start):
            if index == self.alt_start - 1:  # DA3 picks the reference from this block's input
                camera, reference = choose(x)
            x = self.run_per_view(x, [self.pretrained.blocks[index]])
            if index in self.out_layers:
                early.append(torch.cat((x, x), dim=-1))
        output = self.run_alternating(x, grid, camera, global_step, early_out_layers=early)
        return BackboneOutput(output.features, output.camera_tokens, reference_view=reference)

    @staticmethod
    def run_per_view(x: torch.Tensor, blocks: Iterable[nn.Module]) -> torch.Tensor:
        """Blocks before ``alt_start`` (plain DINOv2: no qk-norm, no RoPE) on each view of
        [B, N, T, C]."""
        batch, views, length, dim = x.shape
        flat = x.reshape(batch * views, length, dim)
        for block in blocks:
            flat = block(flat)
        return flat.reshape(x.shape)

    def run_alternating(
        self,
        x: torch.Tensor,
        grid: tuple[int, int],
        camera: torch.Tensor,
        global_step: GlobalStep,
        *,
        early_out_layers: Sequence[torch.Tensor] = (),
    ) -> BackboneOutput:
        """Blocks ``alt_start`` on: ``x`` [B, N, T, C] (the output of block ``alt_start - 1``) with
        token 0 replaced by ``camera`` [B, N, C] -> the heads' inputs (``reference_view`` None).

        Global blocks go through ``global_step`` (full attention, mapping or tracking); the
        exported graphs (``export_onnx/da3_graphs.py``) call this with their own step.
        ``early_out_layers``: the heads' inputs [B, N, T, 2C] of out layers before ``alt_start``.
        """
        local_positions = grid_positions(*grid, num_prefix_tokens=1, device=x.device)
        x = torch.cat((camera.unsqueeze(2), x[:, :, 1:]), dim=2)
        taken = list(early_out_layers) + run_alternating(
            x,
            self.pretrained.blocks,
            start=self.alt_start,
            local_rope=self._rope(local_positions, matmul_dtype(x)),
            global_step=global_step,
            taps=self.out_layers,
        )
        dim = x.shape[-1]
        norm = self.pretrained.norm
        features = [
            torch.cat((out[..., :dim], norm(out[..., dim:])), dim=-1)[:, :, 1:] for out in taken
        ]
        return BackboneOutput(
            features=features, camera_tokens=taken[-1][:, :, 0], reference_view=None
        )

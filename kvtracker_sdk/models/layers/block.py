"""Pre-norm transformer block: ``x + ls1(attn(norm1 x))`` then ``x + ls2(mlp(norm2 x))``.

The same block serves the DINOv2 encoder (LayerScale, no qk-norm), Pi3's decoder (LayerScale,
qk-norm, RoPE2D), Pi3's head decoders (neither LayerScale nor qk-norm) and DA3's backbone. Its
forwards mirror ``Attention``'s uses (plain / map / track / past); everything but the attention is
per token, so they share the rest of the computation.
"""

from __future__ import annotations

import torch
from torch import nn

from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.models.layers.attention import Attention
from kvtracker_sdk.models.layers.layer_scale import LayerScale
from kvtracker_sdk.models.layers.mlp import Mlp
from kvtracker_sdk.models.layers.rope2d import RopeTable
from kvtracker_sdk.models.layers.swiglu import SwiGLUFFN

__all__ = ["FFN_LAYERS", "Block"]

# feed-forward variants by name: GELU MLP (every model but ViT-g) and SwiGLU (DINOv2 ViT-g/14)
FFN_LAYERS: dict[str, type[Mlp] | type[SwiGLUFFN]] = {"mlp": Mlp, "swiglu": SwiGLUFFN}


class Block(nn.Module):
    """One transformer block; names match the checkpoints (``norm1``, ``attn``, ``ls1``, ``mlp``...).

    ``layerscale_init`` None means no LayerScale (``ls1``/``ls2`` are identities without
    parameters, as in Pi3's head decoders). ``ffn`` names the feed-forward network in
    ``FFN_LAYERS`` ("mlp", or "swiglu" for DINOv2 ViT-g backbones).
    """

    def __init__(
        self,
        dim: int,
        num_heads: int,
        *,
        mlp_ratio: float = 4.0,
        qkv_bias: bool = True,
        proj_bias: bool = True,
        ffn_bias: bool = True,
        qk_norm: bool = False,
        layerscale_init: float | None = None,
        norm_eps: float = 1e-6,
        qk_norm_eps: float = 1e-5,
        ffn: str = "mlp",
    ) -> None:
        super().__init__()
        if ffn not in FFN_LAYERS:
            raise ConfigError(f"unknown ffn {ffn!r}; expected one of {sorted(FFN_LAYERS)}")
        self.norm1 = nn.LayerNorm(dim, eps=norm_eps)
        self.attn = Attention(
            dim, num_heads, qkv_bias=qkv_bias, proj_bias=proj_bias, qk_norm=qk_norm, qk_norm_eps=qk_norm_eps
        )
        self.ls1: nn.Module = LayerScale(dim, layerscale_init) if layerscale_init is not None else nn.Identity()
        self.norm2 = nn.LayerNorm(dim, eps=norm_eps)
        self.mlp = FFN_LAYERS[ffn](dim, int(dim * mlp_ratio), bias=ffn_bias)
        self.ls2: nn.Module = LayerScale(dim, layerscale_init) if layerscale_init is not None else nn.Identity()

    def _finish(self, x: torch.Tensor, attended: torch.Tensor) -> torch.Tensor:
        x = x + self.ls1(attended)
        return x + self.ls2(self.mlp(self.norm2(x)))

    def forward(
        self,
        x: torch.Tensor,
        *,
        rope: RopeTable | None = None,
        attn_mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """[B, L, dim] -> [B, L, dim]."""
        return self._finish(x, self.attn(self.norm1(x), rope=rope, attn_mask=attn_mask))

    def forward_map(
        self,
        x: torch.Tensor,
        *,
        rope: RopeTable | None = None,
        attn_mask: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``forward`` plus this block's K/V [B, heads, L, head_dim] (K after k_norm and RoPE)."""
        attended, k, v = self.attn.forward_map(self.norm1(x), rope=rope, attn_mask=attn_mask)
        return self._finish(x, attended), k, v

    def forward_track(
        self,
        x: torch.Tensor,
        key_buffer: torch.Tensor,
        value_buffer: torch.Tensor,
        past_length: int,
        *,
        rope: RopeTable | None = None,
        attn_mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """[1, L, dim] attending over ``past_length`` cached tokens plus itself (see ``Attention``)."""
        attended = self.attn.forward_track(
            self.norm1(x), key_buffer, value_buffer, past_length, rope=rope, attn_mask=attn_mask
        )
        return self._finish(x, attended)

    def forward_past(
        self,
        x: torch.Tensor,
        past_key: torch.Tensor,
        past_value: torch.Tensor,
        past_length: torch.Tensor,
        *,
        rope: RopeTable | None = None,
    ) -> torch.Tensor:
        """[1, L, dim] attending over ``past[:, :, :past_length]`` plus itself, the past read from
        tensors (the exported tracking graphs' form of ``forward_track``; see ``Attention``)."""
        attended = self.attn.forward_past(self.norm1(x), past_key, past_value, past_length, rope=rope)
        return self._finish(x, attended)

"""Transformer building blocks shared by the model families (Pi3, Depth Anything 3).

- ``rope2d``: RoPE2D tables (``grid_positions``, ``rope_table``, ``RopeTable.apply``).
- ``attention``: ``Attention`` (qk-norm, RoPE, SDPA) with plain / map / track uses, and the
  ``CacheBuffers`` protocol a tracking pass reads; ``keyframe_query_mask`` (the attention mask under
  which a full forward equals cached tracking).
- ``block``: the pre-norm ``Block`` (``Mlp`` from ``mlp`` or ``SwiGLUFFN`` from ``swiglu``,
  ``LayerScale`` from ``layer_scale``).
- ``alternating``: the frame/global alternating loop every family runs, with its global steps
  (full, K/V recording, cache tracking, past inputs for exported graphs); ``cache_layout``: which
  blocks are global (``CacheLayout``).
- ``patch_embed``, ``vit_encoder``: the DINOv2 ViT (``DinoViT``) with registers and pos-embed
  interpolation options.
"""

from kvtracker_sdk.models.layers.attention import Attention, CacheBuffers, keyframe_query_mask
from kvtracker_sdk.models.layers.block import Block
from kvtracker_sdk.models.layers.layer_scale import LayerScale
from kvtracker_sdk.models.layers.mlp import Mlp
from kvtracker_sdk.models.layers.patch_embed import PatchEmbed
from kvtracker_sdk.models.layers.rope2d import RopeTable, grid_positions, rope_table
from kvtracker_sdk.models.layers.swiglu import SwiGLUFFN
from kvtracker_sdk.models.layers.vit_encoder import DinoViT

__all__ = [
    "Attention",
    "Block",
    "CacheBuffers",
    "DinoViT",
    "LayerScale",
    "Mlp",
    "PatchEmbed",
    "RopeTable",
    "SwiGLUFFN",
    "grid_positions",
    "keyframe_query_mask",
    "rope_table",
]

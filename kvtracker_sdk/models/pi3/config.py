"""``Pi3Config``: the architecture numbers of a Pi3 network (frozen pydantic model).

``Pi3Config.large()`` is the released model (958,696,738 parameters, ``yyfz233/Pi3``); any smaller
configuration builds a structurally identical network for tests. ``Pi3Config.from_state_dict``
reads the numbers back from a checkpoint's tensor shapes, so small test checkpoints load without a
hand-written configuration.

Fixed by the architecture (not configurable): patch size 14 is a field because checkpoints carry
it, LayerNorm eps 1e-6 (qk-norm 1e-5), RoPE2D positions (registers at (0, 0), patches at
(row+1, col+1)), even decoder blocks attend within a frame and odd blocks globally, and the heads
see concat(output of the second-to-last block, output of the last block).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from pydantic import (
    Field,
    PositiveFloat,
    PositiveInt,
    ValidationError,
    model_validator,
)

from kvtracker_sdk.errors import CheckpointMismatchError
from kvtracker_sdk.models.architecture import ArchitectureConfig
from kvtracker_sdk.models.checkpoint_utils import StateDictShapes

__all__ = ["Pi3Config", "Pi3DecoderConfig", "Pi3EncoderConfig", "Pi3HeadsConfig"]


_Section = ArchitectureConfig  # every section: frozen, unknown keys refused, ConfigError


def _check_heads(name: str, dim: int, heads: int, *, rope: bool) -> None:
    if dim % heads:
        raise ValueError(f"{name}: embed_dim {dim} is not divisible by num_heads {heads}")
    if rope and (dim // heads) % 4:
        raise ValueError(f"{name}: head_dim {dim // heads} must be divisible by 4 for RoPE2D")


class Pi3EncoderConfig(_Section):
    """DINOv2 ViT with registers (``encoder.*``); bicubic antialiased pos-embed resize."""

    embed_dim: PositiveInt = 1024
    depth: PositiveInt = 24
    num_heads: PositiveInt = 16
    mlp_ratio: PositiveFloat = 4.0
    num_register_tokens: int = Field(default=4, ge=0)
    pos_embed_grid: PositiveInt = 37  # pos_embed holds a 37x37 grid (518 px pretraining)

    @model_validator(mode="after")
    def _valid(self) -> Pi3EncoderConfig:
        _check_heads("encoder", self.embed_dim, self.num_heads, rope=False)
        return self


class Pi3DecoderConfig(_Section):
    """The alternating frame/global decoder (``decoder.{i}``, ``register_token``)."""

    embed_dim: PositiveInt = 1024
    depth: PositiveInt = 36
    num_heads: PositiveInt = 16
    mlp_ratio: PositiveFloat = 4.0
    num_register_tokens: PositiveInt = 5
    rope_base: PositiveFloat = 100.0

    @model_validator(mode="after")
    def _valid(self) -> Pi3DecoderConfig:
        _check_heads("decoder", self.embed_dim, self.num_heads, rope=True)
        if self.depth % 2:
            raise ValueError(f"decoder depth must be even (frame/global pairs), got {self.depth}")
        return self

    @property
    def head_dim(self) -> int:
        return self.embed_dim // self.num_heads

    @property
    def global_block_indices(self) -> tuple[int, ...]:
        """Decoder blocks that attend across frames (the cached layers): 1, 3, ..., depth-1."""
        return tuple(range(1, self.depth, 2))


class Pi3HeadsConfig(_Section):
    """The three head decoders (``point_/conf_/camera_decoder``) and their output heads."""

    embed_dim: PositiveInt = 1024
    depth: PositiveInt = 5
    num_heads: PositiveInt = 16
    mlp_ratio: PositiveFloat = 4.0
    point_out_dim: PositiveInt = 1024  # point/conf decoder output = point/conf head input
    camera_out_dim: PositiveInt = 512  # camera decoder output = CameraHead width

    @model_validator(mode="after")
    def _valid(self) -> Pi3HeadsConfig:
        _check_heads("heads", self.embed_dim, self.num_heads, rope=True)
        return self


class Pi3Config(_Section):
    """Architecture of a Pi3 network. ``Pi3Config()`` equals ``Pi3Config.large()``."""

    patch_size: PositiveInt = 14
    encoder: Pi3EncoderConfig = Pi3EncoderConfig()
    decoder: Pi3DecoderConfig = Pi3DecoderConfig()
    heads: Pi3HeadsConfig = Pi3HeadsConfig()

    @model_validator(mode="after")
    def _valid(self) -> Pi3Config:
        # the official model feeds the encoder's patch tokens to the decoder without a projection
        if self.encoder.embed_dim != self.decoder.embed_dim:
            raise ValueError(
                f"encoder.embed_dim {self.encoder.embed_dim} must equal decoder.embed_dim "
                f"{self.decoder.embed_dim}"
            )
        return self

    @classmethod
    def large(cls) -> Pi3Config:
        """The released Pi3: ViT-L/14-reg4 encoder, 36-block 1024-dim decoder, 5-block heads."""
        return cls()

    @classmethod
    def from_state_dict(
        cls,
        state_dict: Mapping[str, torch.Tensor],
        *,
        encoder_num_heads: int | None = None,
        heads_num_heads: int | None = None,
    ) -> Pi3Config:
        """Infer the configuration from a checkpoint's tensor shapes.

        Head counts do not change any weight shape except through the decoder's qk-norm
        (``decoder.0.attn.q_norm.weight`` is [head_dim]); the encoder and the head decoders are
        assumed to use the decoder's head count, as the released model does. Pass
        ``encoder_num_heads`` / ``heads_num_heads`` for checkpoints that differ.
        Raises ``CheckpointMismatchError`` when a needed key is absent or the shapes are
        inconsistent.
        """

        shapes = StateDictShapes(state_dict, "Pi3")
        shape, count = shapes.shape, shapes.count

        dec_dim = shape("decoder.0.norm1.weight")[0]
        dec_heads = dec_dim // shape("decoder.0.attn.q_norm.weight")[0]
        enc_dim = shape("encoder.cls_token")[-1]
        head_dim = shape("point_decoder.projects.weight")[0]
        register_shape = state_dict.get("encoder.register_tokens")
        try:
            return cls(
                patch_size=shape("encoder.patch_embed.proj.weight")[-1],
                encoder=Pi3EncoderConfig(
                    embed_dim=enc_dim,
                    depth=count("encoder.blocks."),
                    num_heads=encoder_num_heads or dec_heads,
                    mlp_ratio=shape("encoder.blocks.0.mlp.fc1.weight")[0] / enc_dim,
                    num_register_tokens=0 if register_shape is None else register_shape.shape[1],
                    pos_embed_grid=math.isqrt(shape("encoder.pos_embed")[1] - 1),
                ),
                decoder=Pi3DecoderConfig(
                    embed_dim=dec_dim,
                    depth=count("decoder."),
                    num_heads=dec_heads,
                    mlp_ratio=shape("decoder.0.mlp.fc1.weight")[0] / dec_dim,
                    num_register_tokens=shape("register_token")[2],
                ),
                heads=Pi3HeadsConfig(
                    embed_dim=head_dim,
                    depth=count("point_decoder.blocks."),
                    num_heads=heads_num_heads or dec_heads,
                    mlp_ratio=shape("point_decoder.blocks.0.mlp.fc1.weight")[0] / head_dim,
                    point_out_dim=shape("point_decoder.linear_out.weight")[0],
                    camera_out_dim=shape("camera_decoder.linear_out.weight")[0],
                ),
            )
        except ValidationError as exc:
            raise CheckpointMismatchError(
                f"the checkpoint's shapes give an invalid Pi3 config: {exc}"
            ) from exc

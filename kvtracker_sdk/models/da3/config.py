"""``DA3Config``: the architecture numbers of a Depth Anything 3 network (frozen pydantic model).

Presets follow the official configs (``da3-{small,base,large,giant}.yaml``):

| preset | dim | heads | depth | ffn | alt_start | out_layers | DPT features / out_channels |
|---|---|---|---|---|---|---|---|
| small | 384 | 6 | 12 | mlp | 4 | 5, 7, 9, 11 | 64 / 48, 96, 192, 384 |
| base | 768 | 12 | 12 | mlp | 4 | 5, 7, 9, 11 | 128 / 96, 192, 384, 768 |
| large | 1024 | 16 | 24 | mlp | 8 | 11, 15, 19, 23 | 256 / 256, 512, 1024, 1024 |
| giant | 1536 | 24 | 40 | swiglu | 13 | 19, 27, 33, 39 | 256 / 256, 512, 1024, 1024 |

Fixed by the architecture: patch 14, head_dim = dim / heads (64 in every preset), LayerScale on
every backbone block, no register tokens, qk-norm and RoPE2D from ``alt_start`` on (the official
``qknorm_start`` and ``rope_start`` equal ``alt_start`` in every config), block ``i`` attends
across views iff ``i >= alt_start`` and ``i`` is odd. The DPT head reads ``cat(local, global)``
features, so its input width is ``2 * dim``; the camera decoder reads the same width; the camera
encoder (``cam_enc``, pose conditioning) is ``dim`` wide.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Literal

import torch
from pydantic import (
    PositiveFloat,
    PositiveInt,
    ValidationError,
    model_validator,
)

from kvtracker_sdk.errors import CheckpointMismatchError, ConfigError
from kvtracker_sdk.models.architecture import ArchitectureConfig
from kvtracker_sdk.models.checkpoint_utils import StateDictShapes
from kvtracker_sdk.models.layers.swiglu import swiglu_hidden_dim

__all__ = ["DA3BackboneConfig", "DA3CameraEncoderConfig", "DA3Config", "DA3HeadConfig"]

# out_layers are not visible in the weights; the official configs use these per depth
_OFFICIAL_OUT_LAYERS = {12: (5, 7, 9, 11), 24: (11, 15, 19, 23), 40: (19, 27, 33, 39)}
_VIT = "backbone.pretrained."  # the backbone's key prefix in a DA3 checkpoint


_Section = ArchitectureConfig  # every section: frozen, unknown keys refused, ConfigError


class DA3BackboneConfig(_Section):
    """The DINOv2 backbone with alternating local/global blocks (``backbone.pretrained.*``)."""

    embed_dim: PositiveInt = 384
    depth: PositiveInt = 12
    num_heads: PositiveInt = 6
    mlp_ratio: PositiveFloat = 4.0
    ffn: Literal["mlp", "swiglu"] = "mlp"
    alt_start: PositiveInt = 4  # first block with camera token, qk-norm and RoPE
    out_layers: tuple[int, int, int, int] = (5, 7, 9, 11)  # blocks feeding the heads
    pos_embed_grid: PositiveInt = 37  # pos_embed holds a 37x37 grid (518 px pretraining)
    rope_base: PositiveFloat = 100.0

    @model_validator(mode="after")
    def _valid(self) -> DA3BackboneConfig:
        if self.embed_dim % self.num_heads:
            raise ValueError(
                f"embed_dim {self.embed_dim} is not divisible by num_heads {self.num_heads}"
            )
        if self.head_dim % 4:
            raise ValueError(f"head_dim {self.head_dim} must be divisible by 4 for RoPE2D")
        if self.alt_start >= self.depth:
            raise ValueError(f"alt_start {self.alt_start} must be < depth {self.depth}")
        if not self.global_block_indices:
            raise ValueError(f"no global block: depth {self.depth}, alt_start {self.alt_start}")
        layers = self.out_layers
        if list(layers) != sorted(set(layers)) or layers[0] < 0 or layers[-1] >= self.depth:
            raise ValueError(
                f"out_layers {layers} must be increasing block indices < depth {self.depth}"
            )
        return self

    @property
    def head_dim(self) -> int:
        return self.embed_dim // self.num_heads

    @property
    def global_block_indices(self) -> tuple[int, ...]:
        """Blocks that attend across views (the cached layers): odd indices from alt_start on."""
        return tuple(i for i in range(self.alt_start, self.depth) if i % 2 == 1)


class DA3HeadConfig(_Section):
    """The DualDPT depth head (``head.*``); its input width is twice the backbone's."""

    features: PositiveInt = 64
    out_channels: tuple[PositiveInt, PositiveInt, PositiveInt, PositiveInt] = (48, 96, 192, 384)

    @model_validator(mode="after")
    def _valid(self) -> DA3HeadConfig:
        # the UV position embedding splits channels into x/y halves of sin/cos pairs
        widths = (*self.out_channels, self.features // 2)
        if any(width % 4 for width in widths):
            raise ValueError(f"DPT widths {widths} must be divisible by 4 (position embedding)")
        return self


class DA3CameraEncoderConfig(_Section):
    """``cam_enc``: pose encoding (9) -> one camera token per view, ``embed_dim`` wide."""

    depth: PositiveInt = 4
    num_heads: PositiveInt = 16
    mlp_ratio: PositiveFloat = 4.0


class DA3Config(_Section):
    """Architecture of a Depth Anything 3 network. ``DA3Config()`` equals ``DA3Config.small()``."""

    patch_size: PositiveInt = 14
    backbone: DA3BackboneConfig = DA3BackboneConfig()
    head: DA3HeadConfig = DA3HeadConfig()
    cam_enc: DA3CameraEncoderConfig = DA3CameraEncoderConfig()

    @model_validator(mode="after")
    def _valid(self) -> DA3Config:
        if self.backbone.embed_dim % self.cam_enc.num_heads:
            raise ValueError(
                f"cam_enc: embed_dim {self.backbone.embed_dim} is not divisible by num_heads "
                f"{self.cam_enc.num_heads}"
            )
        return self

    # ------------------------------------------------------------------ presets
    @classmethod
    def small(cls) -> DA3Config:
        """DA3-Small (ViT-S, 34.3M parameters; weights Apache-2.0)."""
        return cls()

    @classmethod
    def base(cls) -> DA3Config:
        """DA3-Base (ViT-B, 135.4M parameters; weights Apache-2.0)."""
        return cls(
            backbone=DA3BackboneConfig(embed_dim=768, num_heads=12),
            head=DA3HeadConfig(features=128, out_channels=(96, 192, 384, 768)),
        )

    @classmethod
    def large(cls) -> DA3Config:
        """DA3-Large (ViT-L; weights CC BY-NC 4.0)."""
        return cls(
            backbone=DA3BackboneConfig(
                embed_dim=1024, num_heads=16, depth=24, alt_start=8, out_layers=(11, 15, 19, 23)
            ),
            head=DA3HeadConfig(features=256, out_channels=(256, 512, 1024, 1024)),
        )

    @classmethod
    def giant(cls) -> DA3Config:
        """DA3-Giant (ViT-g with SwiGLU; weights CC BY-NC 4.0)."""
        return cls(
            backbone=DA3BackboneConfig(
                embed_dim=1536,
                num_heads=24,
                depth=40,
                ffn="swiglu",
                alt_start=13,
                out_layers=(19, 27, 33, 39),
            ),
            head=DA3HeadConfig(features=256, out_channels=(256, 512, 1024, 1024)),
        )

    @classmethod
    def preset(cls, name: str) -> DA3Config:
        """``"small"``, ``"base"``, ``"large"`` or ``"giant"``."""
        presets = {"small": cls.small, "base": cls.base, "large": cls.large, "giant": cls.giant}
        if name not in presets:
            raise ConfigError(f"unknown DA3 preset {name!r}; expected one of {sorted(presets)}")
        return presets[name]()

    @property
    def preset_name(self) -> str | None:
        """The preset this configuration equals, or None for a custom architecture."""
        for name in ("small", "base", "large", "giant"):
            if self == self.preset(name):
                return name
        return None

    # ------------------------------------------------------------------ inference from weights
    @classmethod
    def from_state_dict(
        cls,
        state_dict: Mapping[str, torch.Tensor],
        *,
        out_layers: tuple[int, int, int, int] | None = None,
        cam_enc_num_heads: int = 16,
    ) -> DA3Config:
        """Infer the configuration from a checkpoint's tensor shapes (keys without ``model.``).

        Two numbers are not visible in the weights: ``out_layers`` (default: the official
        choice for the backbone's depth, else the last four global blocks) and the camera
        encoder's head count (default 16, as in every official config). The backbone's head
        count comes from the qk-norm width (= head_dim). Raises ``CheckpointMismatchError`` when
        a needed key is absent or the shapes are inconsistent.
        """

        shapes = StateDictShapes(state_dict, "DA3")
        shape, count = shapes.shape, shapes.count

        vit = _VIT
        dim = shape(vit + "cls_token")[-1]
        depth = count(vit + "blocks.")
        alt_start = _first_qk_norm_block(state_dict, depth)
        head_dim = shape(f"{vit}blocks.{alt_start}.attn.q_norm.weight")[0]
        swiglu = f"{vit}blocks.0.mlp.w12.weight" in state_dict
        mlp_ratio = _mlp_ratio(shapes, dim, swiglu)
        layers = _out_layers(depth, alt_start, out_layers)
        try:
            return cls(
                patch_size=shape(vit + "patch_embed.proj.weight")[-1],
                backbone=DA3BackboneConfig(
                    embed_dim=dim,
                    depth=depth,
                    num_heads=dim // head_dim,
                    mlp_ratio=mlp_ratio,
                    ffn="swiglu" if swiglu else "mlp",
                    alt_start=alt_start,
                    out_layers=layers,  # type: ignore[arg-type]
                    pos_embed_grid=math.isqrt(shape(vit + "pos_embed")[1] - 1),
                ),
                head=DA3HeadConfig(
                    features=shape("head.scratch.layer1_rn.weight")[0],
                    out_channels=tuple(shape(f"head.projects.{i}.weight")[0] for i in range(4)),  # type: ignore[arg-type]
                ),
                cam_enc=DA3CameraEncoderConfig(
                    depth=count("cam_enc.trunk."),
                    num_heads=cam_enc_num_heads,
                    mlp_ratio=shape("cam_enc.trunk.0.mlp.fc1.weight")[0] / dim,
                ),
            )
        except ValidationError as exc:
            raise CheckpointMismatchError(
                f"the checkpoint's shapes give an invalid DA3 config: {exc}"
            ) from exc



def _first_qk_norm_block(state_dict: Mapping[str, torch.Tensor], depth: int) -> int:
    """``alt_start``: the first backbone block with qk-norm (every later one has it too)."""
    with_qk_norm = [
        i for i in range(depth) if f"{_VIT}blocks.{i}.attn.q_norm.weight" in state_dict
    ]
    if not with_qk_norm:
        raise CheckpointMismatchError(
            "cannot infer a DA3 config: no backbone block has qk-norm (not a DA3 checkpoint?)",
            missing=[f"{_VIT}blocks.{depth - 1}.attn.q_norm.weight"],
        )
    return with_qk_norm[0]


def _mlp_ratio(shapes: StateDictShapes, dim: int, swiglu: bool) -> float:
    """The backbone's MLP ratio from the first block's hidden width; a SwiGLU block whose width
    is the official rounding of ``4 * dim`` reads as ratio 4."""
    if swiglu:
        hidden = shapes.shape(f"{_VIT}blocks.0.mlp.w12.weight")[0] // 2
        return 4.0 if swiglu_hidden_dim(4 * dim) == hidden else 1.5 * hidden / dim
    return shapes.shape(f"{_VIT}blocks.0.mlp.fc1.weight")[0] / dim


def _out_layers(
    depth: int, alt_start: int, out_layers: tuple[int, int, int, int] | None
) -> tuple[int, ...]:
    """The blocks feeding the heads: as given, else the official choice for ``depth``, else the
    last four global blocks; CheckpointMismatchError when that is not four."""
    global_blocks = [i for i in range(alt_start, depth) if i % 2 == 1]
    layers = out_layers or _OFFICIAL_OUT_LAYERS.get(depth) or tuple(global_blocks[-4:])
    if len(layers) != 4:
        raise CheckpointMismatchError(
            f"cannot infer out_layers for a {depth}-block backbone with global blocks {global_blocks}; "
            "pass out_layers=(...) (four block indices) or a config"
        )
    return layers

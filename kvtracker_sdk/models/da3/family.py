"""Depth Anything 3's family record (``models/family.py`` lists what a record answers).

| | Depth Anything 3 |
|---|---|
| checkpoint marker | ``backbone.pretrained.camera_token`` (hub files: ``model.`` prefix) |
| extra tokens per frame | 1 camera token |
| mapping reference | keyframe 0's camera (pinned) |
| outputs | ``conventions.py``: ``pose_enc`` decoded in float64, ``1 - 1/depth_conf``, depth unprojected |
| graphs | ``encoder``, ``decoder_map``, ``decoder_track``, ``head_camera``, ``head_depth`` (DualDPT gives depth and confidence together) |
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from torch import nn

from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.models.da3 import graph_specs
from kvtracker_sdk.models.da3.checkpoint import HUB_REPOS, load_da3
from kvtracker_sdk.models.da3.config import DA3Config
from kvtracker_sdk.models.da3.conventions import frames_from_heads, frames_from_sdk, to_sdk
from kvtracker_sdk.models.da3.model import DepthAnything3
from kvtracker_sdk.models.family import FrameOutputs, LoadedNetwork, MappedFrames, ModelFamily
from kvtracker_sdk.models.graph_io import GraphDef
from kvtracker_sdk.models.layers.attention import CacheBuffers
from kvtracker_sdk.models.layers.cache_layout import CacheLayout
from kvtracker_sdk.types import HeadSet

__all__ = ["DA3Family"]

_MARKERS = frozenset({"backbone.pretrained.camera_token", "model.backbone.pretrained.camera_token"})


class DA3Family(ModelFamily):
    """Depth Anything 3 (Small/Base weights Apache-2.0, Large/Giant CC BY-NC 4.0)."""

    display_name = "Depth Anything 3"
    name = "da3"
    model_type = DepthAnything3
    config_type = DA3Config
    hub_repos = {f"da3-{preset}": repo for preset, repo in HUB_REPOS.items()}
    graph_names = ("encoder", "decoder_map", "decoder_track", "head_camera", "head_depth")

    preset_names = tuple(f"da3-{preset}" for preset in HUB_REPOS)

    def preset_config(self, name: str) -> DA3Config | None:
        return DA3Config.preset(name.removeprefix("da3-")) if name.startswith("da3-") else None

    def owns_checkpoint(self, keys: set[str]) -> bool:
        return bool(keys & _MARKERS)

    def load(self, path: Path, config: Any | None) -> LoadedNetwork:
        loaded = load_da3(path, config=config)
        return LoadedNetwork(loaded.model, loaded.fingerprint, loaded.path)

    def model_name(self, model: nn.Module) -> str:
        return f"da3-{cast(DepthAnything3, model).config.preset_name or 'custom'}"

    def cache_layout(self, model: nn.Module) -> CacheLayout:
        return cast(DepthAnything3, model).backbone.layout

    def extra_tokens_per_frame(self, model: nn.Module) -> int:
        return 1  # the camera token

    def map(self, model: nn.Module, frames: torch.Tensor) -> MappedFrames:
        mapped = cast(DepthAnything3, model).forward_map(
            frames.unsqueeze(0), heads=HeadSet.CONFIDENCE
        )
        outputs = frames_from_sdk(to_sdk(mapped.output, with_points=True))
        return MappedFrames(outputs, mapped.keys, mapped.values, mapped.tokens_per_frame)

    def track(
        self, model: nn.Module, frames: torch.Tensor, cache: CacheBuffers, heads: HeadSet
    ) -> FrameOutputs:
        # DualDPT gives depth and confidence together: CONFIDENCE and ALL cost the same pass
        output = cast(DepthAnything3, model).forward_track(frames, cache, heads=heads)
        return frames_from_sdk(to_sdk(output, with_points=heads is HeadSet.ALL))

    def graphs(self, model: nn.Module) -> list[GraphDef]:
        """``ConfigError`` for a DA3 whose heads read a block before ``alt_start`` (no official
        configuration does; the exported encoder would have to output it)."""
        vit = cast(DepthAnything3, model).config.backbone
        if min(vit.out_layers) < vit.alt_start:
            raise ConfigError(
                f"ONNX export needs DA3 out_layers >= alt_start ({vit.out_layers}, {vit.alt_start})"
            )
        return graph_specs.da3_graphs(cast(DepthAnything3, model).config)

    def example_inputs(self, model: nn.Module, size: tuple[int, int]) -> dict[str, tuple[Any, ...]]:
        return graph_specs.example_inputs(cast(DepthAnything3, model), size)

    def head_graphs(self, heads: HeadSet) -> tuple[str, ...]:
        return ("head_camera",) if heads is HeadSet.CAMERA else ("head_camera", "head_depth")

    def convert_heads(
        self, outputs: Mapping[str, np.ndarray], heads: HeadSet, image_size: tuple[int, int]
    ) -> FrameOutputs:
        return frames_from_heads(
            outputs["pose_enc"],
            image_size,
            depth=outputs.get("depth"),
            depth_conf=outputs.get("depth_conf"),
            with_points=heads is HeadSet.ALL,
        )

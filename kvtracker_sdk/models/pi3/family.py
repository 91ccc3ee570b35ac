"""Pi3's family record (``models/family.py`` lists what a record answers).

| | Pi3 |
|---|---|
| checkpoint marker | ``register_token`` and ``decoder.0.*`` |
| extra tokens per frame | the decoder registers (5) |
| mapping reference | the pass picks its own world frame |
| graphs | ``encoder``, ``decoder_map``, ``decoder_track``, ``head_camera``, ``head_conf``, ``head_points`` |
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from torch import nn

from kvtracker_sdk.models.family import FrameOutputs, LoadedNetwork, MappedFrames, ModelFamily
from kvtracker_sdk.models.graph_io import GraphDef
from kvtracker_sdk.models.layers.attention import CacheBuffers
from kvtracker_sdk.models.layers.cache_layout import CacheLayout
from kvtracker_sdk.models.pi3 import graph_specs
from kvtracker_sdk.models.pi3.checkpoint import load_pi3
from kvtracker_sdk.models.pi3.config import Pi3Config
from kvtracker_sdk.models.pi3.conventions import frames_from_heads, frames_from_output
from kvtracker_sdk.models.pi3.model import Pi3
from kvtracker_sdk.types import HeadSet

__all__ = ["Pi3Family"]

_HEAD_GRAPHS = {
    HeadSet.CAMERA: ("head_camera",),
    HeadSet.CONFIDENCE: ("head_camera", "head_conf"),
    HeadSet.ALL: ("head_camera", "head_conf", "head_points"),
}


class Pi3Family(ModelFamily):
    """π³ (weights CC BY-NC 4.0)."""

    display_name = "Pi3"
    name = "pi3"
    model_type = Pi3
    config_type = Pi3Config
    hub_repos = {"pi3": "yyfz233/Pi3"}
    graph_names = (
        "encoder", "decoder_map", "decoder_track", "head_camera", "head_conf", "head_points",
    )  # fmt: skip

    preset_names = ("large",)  # "pi3" too: the released model's name

    def preset_config(self, name: str) -> Pi3Config | None:
        return Pi3Config.large() if name in ("large", "pi3") else None

    def owns_checkpoint(self, keys: set[str]) -> bool:
        return "register_token" in keys and any(key.startswith("decoder.0.") for key in keys)

    def load(self, path: Path, config: Any | None) -> LoadedNetwork:
        loaded = load_pi3(path, config=config)
        return LoadedNetwork(loaded.model, loaded.fingerprint, loaded.path)

    def model_name(self, model: nn.Module) -> str:
        return "pi3" if cast(Pi3, model).config == Pi3Config.large() else "pi3-custom"

    def cache_layout(self, model: nn.Module) -> CacheLayout:
        return cast(Pi3, model).decoder.layout

    def extra_tokens_per_frame(self, model: nn.Module) -> int:
        return cast(Pi3, model).num_register_tokens

    def map(self, model: nn.Module, frames: torch.Tensor) -> MappedFrames:
        mapped = cast(Pi3, model).forward_map(frames.unsqueeze(0), heads=HeadSet.ALL)
        outputs = frames_from_output(mapped.output)
        return MappedFrames(outputs, mapped.keys, mapped.values, mapped.tokens_per_frame)

    def track(
        self, model: nn.Module, frames: torch.Tensor, cache: CacheBuffers, heads: HeadSet
    ) -> FrameOutputs:
        return frames_from_output(cast(Pi3, model).forward_track(frames, cache, heads=heads))

    def graphs(self, model: nn.Module) -> list[GraphDef]:
        return graph_specs.pi3_graphs(cast(Pi3, model).config)

    def example_inputs(self, model: nn.Module, size: tuple[int, int]) -> dict[str, tuple[Any, ...]]:
        return graph_specs.example_inputs(cast(Pi3, model), size)

    def head_graphs(self, heads: HeadSet) -> tuple[str, ...]:
        return _HEAD_GRAPHS[heads]

    def convert_heads(
        self, outputs: Mapping[str, np.ndarray], heads: HeadSet, image_size: tuple[int, int]
    ) -> FrameOutputs:
        return frames_from_heads(
            outputs["rotation_raw"],
            outputs["translation"],
            outputs.get("conf_logits"),
            outputs.get("local_points"),
        )

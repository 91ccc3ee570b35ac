"""What a model family provides to the SDK: one record per family, listed in ``registry.py``.

A family is a folder ``models/<family>/`` with its network, and a ``family.py`` holding a
``ModelFamily`` subclass; ``models/registry.py`` lists one instance per family. Everything the
SDK does per family goes through the record, so adding a family (VGGT, MapAnything, ...) is that
folder and one registry line:

| member | what it answers |
|---|---|
| ``name``, ``display_name``, ``model_type``, ``config_type`` | identity: ``"pi3"``, ``"Pi3"``, the ``nn.Module``, its pydantic config |
| ``hub_repos`` | user-facing model names -> official hub repositories (``MODEL_NAMES``) |
| ``preset_names``, ``preset_config(name)`` | architectures by name (``export-onnx --config``) |
| ``owns_checkpoint(keys)`` | whether a checkpoint's tensor names are this family's |
| ``load(path, config)`` | the network from a ``.safetensors`` file, strictly, with its weights fingerprint |
| ``build(config)`` | a network with random weights (tests, benchmarks, exports of a config) |
| ``model_name(model)`` | ``"pi3"``, ``"da3-small"``, ... or ``"<family>-custom"`` |
| ``cache_layout(model)``, ``extra_tokens_per_frame(model)`` | the cached global layers and the tokens per frame besides patches |
| ``map(model, frames)``, ``track(model, frames, cache, heads)`` | the PyTorch passes, outputs in the SDK's conventions |
| ``graph_names``, ``graphs(model)``, ``example_inputs(model, size)`` | the exported graphs: modules over the model's own stages, their signatures, example arguments |
| ``head_graphs(heads)``, ``convert_heads(outputs, heads, size)`` | which head graphs a ``HeadSet`` runs, and their outputs in the SDK's conventions |

SDK conventions (``FrameOutputs``): ``T_world_cam`` camera-to-world float64 [F, 4, 4] (OpenCV
axes), confidence float32 [F, H, W] in [0, 1], local points float32 [F, H, W, 3] in the camera
frame; arrays on the CPU.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Protocol

import numpy as np
import torch
from pydantic import BaseModel
from torch import nn

from kvtracker_sdk.models.graph_io import GraphDef
from kvtracker_sdk.models.layers.attention import CacheBuffers
from kvtracker_sdk.models.layers.cache_layout import CacheLayout
from kvtracker_sdk.types import HeadSet

__all__ = ["FrameOutputs", "LoadedNetwork", "MappedFrames", "ModelFamily", "Network"]


@dataclass(frozen=True)
class FrameOutputs:
    """Per-frame outputs of a pass over F frames, SDK conventions, numpy on the CPU."""

    poses: np.ndarray  # [F, 4, 4] float64 T_world_cam
    confidence: np.ndarray | None = None  # [F, H, W] float32 in [0, 1]
    local_points: np.ndarray | None = None  # [F, H, W, 3] float32, camera frame
    intrinsics: np.ndarray | None = None  # [F, 3, 3] float64 pixels, if predicted (DA3)


@dataclass(frozen=True)
class MappedFrames:
    """A mapping pass: per-keyframe outputs and the cache content."""

    frames: FrameOutputs
    keys: list[torch.Tensor]  # per global layer [1, heads, N*T, head_dim]
    values: list[torch.Tensor]
    tokens_per_frame: int


class Network(Protocol):
    """What the SDK reads of every family's network, besides its being an ``nn.Module``."""

    @property
    def config(self) -> Any: ...  # pydantic: ``config_hash``, ``patch_size``, ``model_dump()``

    @property
    def compute_dtype(self) -> torch.dtype: ...  # the trunk's matrix products': the KV cache's

    def set_precision(self, dtype: torch.dtype) -> Any: ...  # trunk matmuls in ``dtype``; returns self

    def tokens_per_frame(self, height: int, width: int) -> int: ...


@dataclass(frozen=True)
class LoadedNetwork:
    """A network read from a checkpoint (fp32, CPU, eval mode) and the hash of its weights."""

    model: nn.Module
    fingerprint: str
    path: Path


def numpy_or_none(tensor: torch.Tensor | None) -> np.ndarray | None:
    return None if tensor is None else tensor.detach().cpu().numpy()


class ModelFamily(ABC):
    """One family's record (see the module docstring for what each member answers)."""

    name: ClassVar[str]
    display_name: ClassVar[str]  # in messages: "Pi3", "Depth Anything 3"
    model_type: ClassVar[type[nn.Module]]
    config_type: ClassVar[type[BaseModel]]
    hub_repos: ClassVar[Mapping[str, str]]  # model name -> hub repository
    graph_names: ClassVar[tuple[str, ...]]  # the export's graphs, in the order they run
    preset_names: ClassVar[tuple[str, ...]]  # architectures a user may name (``--config``)

    # ------------------------------------------------------------------ checkpoints
    @abstractmethod
    def owns_checkpoint(self, keys: set[str]) -> bool: ...

    @abstractmethod
    def load(self, path: Path, config: Any | None) -> LoadedNetwork: ...

    @abstractmethod
    def preset_config(self, name: str) -> BaseModel | None:
        """The architecture called ``name`` (one of ``preset_names``), None if not this
        family's; ``ConfigError`` for a name of this family that no preset has."""

    def build(self, config: Any) -> nn.Module:
        """A network of ``config`` with PyTorch's random init (seed it first), eval mode."""
        return self.model_type(config).eval()

    @abstractmethod
    def model_name(self, model: nn.Module) -> str: ...

    # ------------------------------------------------------------------ cache
    @abstractmethod
    def cache_layout(self, model: nn.Module) -> CacheLayout: ...

    @abstractmethod
    def extra_tokens_per_frame(self, model: nn.Module) -> int: ...

    # ------------------------------------------------------------------ PyTorch passes
    @abstractmethod
    def map(self, model: nn.Module, frames: torch.Tensor) -> MappedFrames:
        """Keyframes float [N, 3, H, W] in [0, 1] -> outputs (all heads) and the cache content."""

    @abstractmethod
    def track(
        self, model: nn.Module, frames: torch.Tensor, cache: CacheBuffers, heads: HeadSet
    ) -> FrameOutputs:
        """Independent query frames float [F, 3, H, W] in [0, 1] against ``cache``."""

    # ------------------------------------------------------------------ exported graphs
    @abstractmethod
    def graphs(self, model: nn.Module) -> list[GraphDef]:
        """The export's graphs (``ConfigError`` for a network that cannot be exported)."""

    @abstractmethod
    def example_inputs(self, model: nn.Module, size: tuple[int, int]) -> dict[str, tuple[Any, ...]]:
        """Example arguments of every graph at ``size`` (H, W), computed with PyTorch."""

    @abstractmethod
    def head_graphs(self, heads: HeadSet) -> tuple[str, ...]: ...

    @abstractmethod
    def convert_heads(
        self, outputs: Mapping[str, np.ndarray], heads: HeadSet, image_size: tuple[int, int]
    ) -> FrameOutputs:
        """The head graphs' outputs (by name, F frames) in the SDK's conventions."""

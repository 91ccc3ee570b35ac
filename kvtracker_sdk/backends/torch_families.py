"""What ``TorchBackend`` needs from each model family, in the SDK's conventions.

A family adapter wraps one network and answers in numpy, in the conventions of
``backends/base.py``: ``T_world_cam`` camera-to-world float64, confidence in [0, 1], local points
in the camera frame (OpenCV axes). The backend itself (input checks, cache checks, locking,
timings) is then the same for every family.

| | Pi3 | Depth Anything 3 |
|---|---|---|
| pose | ``camera_poses`` (camera-to-world) | ``pose_enc`` decoded in float64 (DA3's ``extrinsics`` are world-to-camera) |
| confidence | ``sigmoid(conf logit)`` | ``1 - 1/depth_conf`` (= sigmoid of DA3's logit; ``depth_conf`` >= 1) |
| local points | predicted directly | ``depth * K⁻¹ (u, v, 1)`` from depth and the predicted intrinsics |
| extra tokens per frame | 5 registers | 1 camera token |
| mapping reference | the pass picks its own frame | keyframe 0's camera (pinned) |
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from kvtracker_sdk.cache.kv_cache import CacheLayout, KVCache
from kvtracker_sdk.errors import ModelError
from kvtracker_sdk.models.da3 import DepthAnything3, to_sdk
from kvtracker_sdk.models.pi3 import Pi3
from kvtracker_sdk.models.registry import Family
from kvtracker_sdk.types import HeadSet

__all__ = [
    "DA3Family",
    "FrameOutputs",
    "MappedFrames",
    "Pi3Family",
    "TorchFamily",
    "family_adapter",
]


@dataclass(frozen=True)
class FrameOutputs:
    """Per-frame outputs of a pass over F frames, SDK conventions, on the CPU."""

    poses: np.ndarray  # [F, 4, 4] float64 T_world_cam
    confidence: np.ndarray | None = None  # [F, H, W] float32 in [0, 1]
    local_points: np.ndarray | None = None  # [F, H, W, 3] float32, camera frame


@dataclass(frozen=True)
class MappedFrames:
    """A mapping pass: per-keyframe outputs and the cache content."""

    frames: FrameOutputs
    keys: list[torch.Tensor]  # per global layer [1, heads, N*T, head_dim]
    values: list[torch.Tensor]
    tokens_per_frame: int


class TorchFamily(Protocol):
    """One family's network behind ``TorchBackend`` (frames are float [F, 3, H, W] in [0, 1])."""

    family: Family
    layout: CacheLayout
    extra_tokens_per_frame: int

    @property
    def compute_dtype(self) -> torch.dtype: ...

    def map(self, frames: torch.Tensor) -> MappedFrames: ...

    def track(self, frames: torch.Tensor, cache: KVCache, heads: HeadSet) -> FrameOutputs: ...


def _numpy(tensor: torch.Tensor | None) -> np.ndarray | None:
    return None if tensor is None else tensor.detach().cpu().numpy()


class Pi3Family:
    """Pi3: poses, confidence logits and local points come straight from its heads."""

    family: Family = "pi3"

    def __init__(self, model: Pi3) -> None:
        self.model = model
        decoder = model.decoder
        self.layout = CacheLayout(decoder.global_block_indices, decoder.num_heads, decoder.head_dim)
        self.extra_tokens_per_frame = model.num_register_tokens

    @property
    def compute_dtype(self) -> torch.dtype:
        return self.model.compute_dtype

    def map(self, frames: torch.Tensor) -> MappedFrames:
        mapped = self.model.forward_map(frames.unsqueeze(0), heads=HeadSet.ALL)
        output = mapped.output
        assert output.conf is not None and output.local_points is not None  # HeadSet.ALL
        outputs = FrameOutputs(
            poses=output.camera_poses[0].double().cpu().numpy(),
            confidence=torch.sigmoid(output.conf[0, ..., 0]).cpu().numpy(),
            local_points=output.local_points[0].cpu().numpy(),
        )
        return MappedFrames(outputs, mapped.keys, mapped.values, mapped.tokens_per_frame)

    def track(self, frames: torch.Tensor, cache: KVCache, heads: HeadSet) -> FrameOutputs:
        output = self.model.forward_track(frames, cache, heads=heads)  # [F, 1, ...]
        conf = None if output.conf is None else torch.sigmoid(output.conf[:, 0, ..., 0])
        points = None if output.local_points is None else output.local_points[:, 0]
        return FrameOutputs(
            poses=output.camera_poses[:, 0].double().cpu().numpy(),
            confidence=_numpy(conf),
            local_points=_numpy(points),
        )


class DA3Family:
    """Depth Anything 3: outputs converted by ``models.da3.to_sdk`` (see the table above)."""

    family: Family = "da3"
    extra_tokens_per_frame = 1  # the camera token

    def __init__(self, model: DepthAnything3) -> None:
        self.model = model
        backbone = model.backbone
        self.layout = CacheLayout(
            backbone.global_block_indices, backbone.num_heads, backbone.head_dim
        )

    @property
    def compute_dtype(self) -> torch.dtype:
        return self.model.compute_dtype

    def map(self, frames: torch.Tensor) -> MappedFrames:
        mapped = self.model.forward_map(frames.unsqueeze(0), heads=HeadSet.CONFIDENCE)
        sdk = to_sdk(mapped.output, with_points=True)
        assert sdk.confidence is not None and sdk.local_points is not None  # DualDPT ran
        outputs = FrameOutputs(
            poses=sdk.T_world_cam[0].cpu().numpy(),
            confidence=sdk.confidence[0].cpu().numpy(),
            local_points=sdk.local_points[0].cpu().numpy(),
        )
        return MappedFrames(outputs, mapped.keys, mapped.values, mapped.tokens_per_frame)

    def track(self, frames: torch.Tensor, cache: KVCache, heads: HeadSet) -> FrameOutputs:
        # DualDPT gives depth and confidence together: CONFIDENCE and ALL cost the same pass
        output = self.model.forward_track(frames, cache, heads=heads)  # [F, 1, ...]
        sdk = to_sdk(output, with_points=heads is HeadSet.ALL)
        conf = None if sdk.confidence is None else sdk.confidence[:, 0]
        points = None if sdk.local_points is None else sdk.local_points[:, 0]
        return FrameOutputs(
            poses=sdk.T_world_cam[:, 0].cpu().numpy(),
            confidence=_numpy(conf),
            local_points=_numpy(points),
        )


def family_adapter(model: Pi3 | DepthAnything3) -> TorchFamily:
    """The adapter of ``model``'s family; ``ModelError`` for any other network."""
    if isinstance(model, Pi3):
        return Pi3Family(model)
    if isinstance(model, DepthAnything3):
        return DA3Family(model)
    raise ModelError(f"{type(model).__name__} is neither a Pi3 nor a DepthAnything3 network")

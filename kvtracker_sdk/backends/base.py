"""The ``Backend`` contract: what the tracker needs from a network, and nothing more.

A backend is stateless with respect to the map. It turns keyframe images into a map (poses in the
pass's own raw frame, per-pixel confidence and points, and a ``KVCache``), and tracks one image
against a cache. Images arrive already at the model resolution (``kvtracker_sdk/preprocess``), as
uint8 RGB [N, H, W, 3] — the same bytes a map file stores, so a rebuild after reloading a map sees
exactly what the original mapping saw.

Two backends whose ``info.fingerprint`` and ``info.layout`` agree compute the same function, so a
cache made by one can be used by the other (live backend swap; maps saved by one, loaded by the
other). The fingerprint hashes the model family, its configuration and its weights — not the
runtime (torch/onnx), device or dtype.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
import torch

from kvtracker_sdk.cache.backend_info import BackendInfo
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.types import HeadSet

__all__ = ["Backend", "BackendInfo", "MapResult", "TrackResult"]


def _readonly(array: np.ndarray | None) -> np.ndarray | None:
    if array is not None:
        array.setflags(write=False)
    return array


@dataclass(frozen=True)
class MapResult:
    """A mapping pass over N keyframes, in the pass's own raw world frame and scale."""

    poses: np.ndarray  # [N, 4, 4] float64 T_world_cam, raw frame of this pass
    confidence: np.ndarray  # [N, H, W] float32 in [0, 1]
    local_points: np.ndarray  # [N, H, W, 3] float32, camera frame (OpenCV axes), raw scale
    cache: KVCache
    timings_ms: Mapping[str, float] = field(default_factory=dict)
    # [N, 3, 3] float64 pixels of the model-resolution images, when the network predicts them
    intrinsics: np.ndarray | None = None

    def __post_init__(self) -> None:
        for array in (self.poses, self.confidence, self.local_points, self.intrinsics):
            _readonly(array)

    @property
    def num_frames(self) -> int:
        return int(self.poses.shape[0])

    @classmethod
    def of_pass(
        cls,
        poses: np.ndarray,
        confidence: np.ndarray | None,
        local_points: np.ndarray | None,
        keys: Sequence[torch.Tensor],
        values: Sequence[torch.Tensor],
        *,
        info: BackendInfo,
        image_size: tuple[int, int],
        map_ms: float,
        intrinsics: np.ndarray | None = None,
    ) -> MapResult:
        """A mapping pass's per-keyframe outputs (all heads) and the K/V of its global layers
        [1, heads, N*T, head_dim] -> a ``MapResult`` whose cache lists keyframes 0..N-1."""
        assert confidence is not None and local_points is not None  # mapping runs every head
        cache = KVCache.from_layers(
            list(keys),
            list(values),
            layout=info.layout,
            tokens_per_frame=info.tokens_per_frame(*image_size),
            keyframe_ids=range(poses.shape[0]),
        )
        return cls(
            poses, confidence, local_points, cache, timings_ms={"map": map_ms},
            intrinsics=intrinsics,
        )


@dataclass(frozen=True)
class TrackResult:
    """One frame tracked against a cache, in the cache's raw frame."""

    pose: np.ndarray  # [4, 4] float64 T_world_cam
    confidence: float | None  # mean per-pixel confidence in [0, 1]; None if not computed
    confidence_map: np.ndarray | None = None  # [H, W] float32 in [0, 1]
    local_points: np.ndarray | None = None  # [H, W, 3] float32 camera frame
    timings_ms: Mapping[str, float] = field(default_factory=dict)
    # [3, 3] float64 pixels of the model-resolution image, when the network predicts them (DA3)
    intrinsics: np.ndarray | None = None

    def __post_init__(self) -> None:
        for array in (self.pose, self.confidence_map, self.local_points, self.intrinsics):
            _readonly(array)


@runtime_checkable
class Backend(Protocol):
    """What every backend (torch, onnx, openvino, simulated, an app's own) implements.

    A backend written outside the package works with ``Tracker`` when it provides:

    * ``info`` -> :class:`BackendInfo`: ``backend`` (the runtime's name), ``model``, ``family``
      (which frame preprocessing it gets, and which maps it may load: caches never cross
      families), ``config_hash`` and ``weights_fingerprint`` (together the ``fingerprint``
      saved maps are checked against), ``patch_size`` (model inputs are multiples of it),
      ``extra_tokens_per_frame``, ``layout`` (the ``CacheLayout`` of its caches), ``dtype``,
      ``device``. It must not change while a tracker uses the backend.
    * ``map(images, masks=None)`` -> :class:`MapResult` for uint8 RGB [N, H, W, 3] at model
      resolution: ``poses`` [N, 4, 4] T_world_cam (OpenCV axes) in the pass's own frame and
      scale, ``confidence`` [N, H, W] in [0, 1], ``local_points`` [N, H, W, 3] in each camera's
      frame, and a ``KVCache`` listing keyframes 0..N-1 (``MapResult.of_pass`` builds one from
      per-layer K/V).
    * ``track(image, cache, *, heads)`` -> :class:`TrackResult` for one uint8 [H, W, 3] image
      against a cache this backend's ``map`` made: ``pose`` [4, 4] in the cache's frame; with
      ``heads`` CONFIDENCE or ALL a mean ``confidence`` and ``confidence_map`` [H, W], with ALL
      also ``local_points``. It must not change the cache beyond its scratch region.
    * ``close()``: idempotent; a tracker never closes a backend it was given.
    * its family's preprocessing: either ``kvtracker_sdk.preprocess.register_family(family,
      preprocessing)`` once, or an attribute ``preprocessing`` (a
      :class:`~kvtracker_sdk.preprocess.Preprocessing`) on the backend; the latter wins.

    Optional: ``intrinsics`` in the results (pixels of the model-resolution images) when the
    network predicts a camera. Bad input raises a typed ``kvtracker_sdk.errors`` error; any other
    exception from ``map`` / ``track`` is reported by the tracker as a backend failure.
    """

    @property
    def info(self) -> BackendInfo: ...

    def map(self, images: np.ndarray, masks: np.ndarray | None = None) -> MapResult:
        """Mapping pass with full attention over ``images`` uint8 [N, H, W, 3].

        ``masks`` (bool [N, H, W]) are advisory: backends may use them, the tracker uses them
        for confidence summaries. Poses come back in the pass's own raw frame.
        """
        ...

    def track(
        self, image: np.ndarray, cache: KVCache, *, heads: HeadSet = HeadSet.CONFIDENCE
    ) -> TrackResult:
        """Track one image uint8 [H, W, 3] against ``cache`` (its global attention reads it)."""
        ...

    def close(self) -> None:
        """Release resources (threads, sessions). Idempotent."""
        ...

"""``KeyframeMap``: the map as plain data — keyframes, their KV cache, and the gauge.

This is exactly what a map file stores (``io/map_file/map_file.py`` reads and writes it without knowing the
tracker). The tracker owns one and replaces it as a whole on every accepted rebuild, so the
previous map stays intact for a revert and for readers on other threads.

Frames: ``keyframes[i].T_world_cam`` is in the tracker's *world* frame (keyframe 0 of the first map
is the identity). The cache's K/V come from the latest mapping pass, whose raw frame is mapped to
the world frame by ``gauge`` (a Sim(3): ``world = gauge(raw)``); a pose tracked against the cache
comes back in the raw frame and goes through the gauge.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.world import MapWorld

__all__ = ["LEGACY_PREPROCESSING", "Keyframe", "KeyframeMap"]

# The preprocessing of maps that do not record one (saved before it was recorded): the name of
# ``kvtracker_sdk.preprocess.LEGACY_AREA_FLOOR``.
LEGACY_PREPROCESSING = "legacy-area-floor"


@dataclass(frozen=True)
class Keyframe:
    """One keyframe at model resolution."""

    keyframe_id: int  # unique within a session, never reused
    frame_index: int  # index of the frame it came from in the session
    timestamp: float | None
    image: np.ndarray  # uint8 [H, W, 3] RGB, at model resolution (after object-mode masking)
    mask: np.ndarray | None  # bool [H, W] (object mode) or None
    T_world_cam: np.ndarray  # float64 [4, 4], world frame
    confidence_map: np.ndarray  # float32 [H, W] in [0, 1], from the latest mapping pass
    local_points: np.ndarray  # float32 [H, W, 3], camera frame, world scale
    mean_confidence: float  # mean confidence over the mask (all pixels without a mask)
    # float32 [H, W] metres from a depth sensor, registered and resized to the model image (0 =
    # invalid); None without one. Kept in memory for the metric scale, not saved in map files.
    sensor_depth: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name in ("image", "mask", "T_world_cam", "confidence_map", "local_points",
                     "sensor_depth"):
            value = getattr(self, name)
            if value is not None:
                value.setflags(write=False)

    def world_points(self) -> np.ndarray:
        """[H, W, 3] points of this keyframe in the world frame."""
        R = self.T_world_cam[:3, :3]
        t = self.T_world_cam[:3, 3]
        return self.local_points.astype(np.float64) @ R.T + t


@dataclass(frozen=True)
class KeyframeMap:
    """The map: keyframes (world frame), the KV cache of their latest mapping pass, the gauge."""

    keyframes: tuple[Keyframe, ...]
    cache: KVCache
    gauge: Sim3  # raw frame of `cache`'s mapping pass -> world frame
    generation: int = 0
    resolution: tuple[int, int] = (0, 0)  # (H, W) model input
    metadata: dict[str, str] = field(default_factory=dict)
    preprocessing: str = LEGACY_PREPROCESSING  # name of what prepared the keyframe images
    # keyframes inserted incrementally since the last full mapping pass (not saved in files)
    insertions: int = 0
    # the world frame's units and axes (metric? gravity-aligned?): the map file's "world" field
    world: MapWorld = MapWorld()

    @property
    def num_keyframes(self) -> int:
        return len(self.keyframes)

    @property
    def keyframe_ids(self) -> tuple[int, ...]:
        return tuple(kf.keyframe_id for kf in self.keyframes)

    def keyframe(self, keyframe_id: int) -> Keyframe:
        for kf in self.keyframes:
            if kf.keyframe_id == keyframe_id:
                return kf
        raise KeyError(keyframe_id)

    def poses(self) -> np.ndarray:
        """[N, 4, 4] keyframe T_world_cam."""
        return np.stack([kf.T_world_cam for kf in self.keyframes])

    def with_generation(self, generation: int) -> KeyframeMap:
        return replace(self, generation=generation)

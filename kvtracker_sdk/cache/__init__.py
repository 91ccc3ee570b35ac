"""Layer 2: the map as data — the KV cache and the keyframes it belongs to."""

from kvtracker_sdk.cache.keyframe_map import Keyframe, KeyframeMap
from kvtracker_sdk.cache.kv_cache import CacheLayout, KVCache

__all__ = ["CacheLayout", "Keyframe", "KeyframeMap", "KVCache"]

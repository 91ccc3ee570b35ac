"""``BackendInfo``: which function a backend computes, and so which caches and maps it can use.

It lives with the cache (layer 2), not with the backends: map files (``io/``) record and check it,
and they need nothing else of a backend. ``backends.base`` re-exports it.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

from kvtracker_sdk.cache.kv_cache import CacheLayout

__all__ = ["BackendInfo"]


@dataclass(frozen=True)
class BackendInfo:
    """Identity and properties of a backend."""

    backend: str  # runtime: "torch", "onnx", "openvino", "simulated"
    model: str  # e.g. "pi3", "da3-small", "pi3-custom"
    family: str  # "pi3", "da3", "simulated": caches never cross families
    config_hash: str  # hash of the architecture configuration
    weights_fingerprint: str  # hash of the weights (content, not path)
    patch_size: int
    extra_tokens_per_frame: int  # tokens per frame besides the patches (Pi3: 5 registers)
    layout: CacheLayout
    dtype: str  # compute / cache dtype, e.g. "float32", "bfloat16"
    device: str = "cpu"
    accelerations: tuple[str, ...] = ()  # optional fast paths detected at construction

    @property
    def fingerprint(self) -> str:
        """Identity of the function computed: family + config + weights (16 hex chars)."""
        text = f"{self.family}|{self.config_hash}|{self.weights_fingerprint}"
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def tokens_per_frame(self, height: int, width: int) -> int:
        return self.extra_tokens_per_frame + (height // self.patch_size) * (width // self.patch_size)

"""``CacheLayout``: which blocks of a network are global (their K/V are cached) and their shape.

Every family's record states its network's layout (``ModelFamily.cache_layout``); ``KVCache``
(``cache/``, which re-exports this class) allocates its buffers from it, and the tracking step
checks a cache against it before touching the cache.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from numbers import Integral
from typing import Any

import torch

from kvtracker_sdk.errors import CacheError
from kvtracker_sdk.models.layers.attention import CacheBuffers, check_cache_buffers

__all__ = ["CacheLayout"]


def _is_count(value: object, minimum: int) -> bool:
    return isinstance(value, Integral) and not isinstance(value, bool) and int(value) >= minimum


@dataclass(frozen=True)
class CacheLayout:
    """Shape of a model's cache: which blocks are global, heads and head_dim per layer."""

    block_indices: tuple[int, ...]  # decoder/backbone block index of each cached global layer
    num_heads: int
    head_dim: int

    def __post_init__(self) -> None:
        # checked here so that a bad layout is a CacheError, not torch's RuntimeError later
        sizes = (self.num_heads, self.head_dim)
        if not all(_is_count(v, 1) for v in sizes):
            raise CacheError(f"num_heads and head_dim must be integers >= 1, got {sizes}")
        indices = tuple(self.block_indices)
        if not all(_is_count(i, 0) for i in indices):
            raise CacheError(f"block indices must be integers >= 0, got {indices}")

    @property
    def num_layers(self) -> int:
        return len(self.block_indices)

    def bytes_per_token(self, dtype: torch.dtype) -> int:
        """K and V of one token in every layer."""
        itemsize = torch.empty((), dtype=dtype).element_size()
        return 2 * self.num_layers * self.num_heads * self.head_dim * itemsize

    def check_cache(self, cache: CacheBuffers, *, dtype: torch.dtype, device: torch.device) -> None:
        """Raise ``CacheError`` unless every global layer has buffers of the right shape and dtype."""
        check_cache_buffers(
            cache,
            block_indices=self.block_indices,
            num_heads=self.num_heads,
            head_dim=self.head_dim,
            dtype=dtype,
            device=device,
        )

    def to_dict(self) -> dict[str, object]:
        return {
            "block_indices": list(self.block_indices),
            "num_heads": self.num_heads,
            "head_dim": self.head_dim,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> CacheLayout:
        return cls(
            block_indices=tuple(int(i) for i in data["block_indices"]),
            num_heads=int(data["num_heads"]),
            head_dim=int(data["head_dim"]),
        )

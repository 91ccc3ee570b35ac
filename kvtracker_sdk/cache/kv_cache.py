"""``KVCache``: the keys and values of every keyframe token, per global-attention layer.

This is KV-Tracker's map in tensor form. For each global layer ``i`` the cache holds
``K_i, V_i`` of shape [1, heads, length, head_dim] where ``length = num_keyframes * tokens_per_frame``
and tokens run keyframe by keyframe. K is stored exactly as it enters the attention (after
qk-norm and RoPE), so a tracking pass only has to attend to it.

Why preallocated buffers: the official code grows the cache with ``torch.cat`` in all layers for
every tracked frame (294 ms per step at 32 keyframes in fp32, 653 ms at 64). Here every layer owns
one buffer with spare capacity: a tracking pass writes its own K/V into the scratch region right
after ``length`` and attends over ``[:length + query_tokens]`` — a copy of the query's tokens only.
Appending a keyframe writes into the spare capacity; the buffer grows geometrically when full.

Concurrency: the scratch region is shared, so one tracking pass at a time per cache; callers hold
``cache.lock`` around a pass (backends do). Different caches (e.g. the previous map and a map being
rebuilt on a worker thread) are fully independent.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence

import torch

from kvtracker_sdk.errors import CacheError
from kvtracker_sdk.models.layers.cache_layout import CacheLayout

__all__ = ["CacheLayout", "KVCache"]


class KVCache:
    """Per-layer K/V of the keyframes in preallocated buffers with an explicit length."""

    def __init__(
        self,
        layout: CacheLayout,
        tokens_per_frame: int,
        *,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str = "cpu",
        capacity_frames: int = 8,
    ) -> None:
        if tokens_per_frame <= 0:
            raise CacheError(f"tokens_per_frame must be > 0, got {tokens_per_frame}")
        self.layout = layout
        self.tokens_per_frame = int(tokens_per_frame)
        self.dtype = dtype
        self.device = torch.device(device)
        self.lock = threading.RLock()
        self._keyframe_ids: list[int] = []
        capacity = max(1, capacity_frames) * self.tokens_per_frame
        shape = (1, layout.num_heads, capacity, layout.head_dim)
        self._keys = [torch.empty(shape, dtype=dtype, device=self.device) for _ in layout.block_indices]
        self._values = [torch.empty(shape, dtype=dtype, device=self.device) for _ in layout.block_indices]

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_layers(
        cls,
        keys: Sequence[torch.Tensor],
        values: Sequence[torch.Tensor],
        *,
        layout: CacheLayout,
        tokens_per_frame: int,
        keyframe_ids: Sequence[int],
        spare_frames: int = 2,
    ) -> KVCache:
        """Wrap the per-layer K/V of a mapping pass ([1 or none, H, N*T, D] each)."""
        if len(keys) != layout.num_layers or len(values) != layout.num_layers:
            raise CacheError(
                f"expected {layout.num_layers} layers of K and V, got {len(keys)} and {len(values)}"
            )
        n = len(keyframe_ids)
        first = keys[0] if keys[0].dim() == 4 else keys[0].unsqueeze(0)
        cache = cls(
            layout,
            tokens_per_frame,
            dtype=first.dtype,
            device=first.device,
            capacity_frames=n + max(1, spare_frames),
        )
        length = n * tokens_per_frame
        for i, (k, v) in enumerate(zip(keys, values, strict=True)):
            k4 = k if k.dim() == 4 else k.unsqueeze(0)
            v4 = v if v.dim() == 4 else v.unsqueeze(0)
            expected = (1, layout.num_heads, length, layout.head_dim)
            if tuple(k4.shape) != expected or tuple(v4.shape) != expected:
                raise CacheError(
                    f"layer {i}: K {tuple(k4.shape)} / V {tuple(v4.shape)} do not match {expected}"
                )
            cache._keys[i][:, :, :length].copy_(k4)
            cache._values[i][:, :, :length].copy_(v4)
        cache._keyframe_ids = [int(i) for i in keyframe_ids]
        return cache

    @classmethod
    def preallocated(
        cls,
        layout: CacheLayout,
        tokens_per_frame: int,
        keyframe_ids: Sequence[int],
        *,
        dtype: torch.dtype,
        spare_frames: int = 2,
    ) -> KVCache:
        """A CPU cache listing ``keyframe_ids`` whose K/V are not written yet: the caller fills
        ``buffers(i)[:, :, :length]`` next (a map loader reads a file straight into place,
        without an intermediate copy)."""
        ids = [int(i) for i in keyframe_ids]
        if len(set(ids)) != len(ids):
            raise CacheError(f"keyframe ids must be distinct, got {ids}")
        cache = cls(
            layout, tokens_per_frame, dtype=dtype, capacity_frames=len(ids) + max(1, spare_frames)
        )
        cache._keyframe_ids = ids
        return cache

    # ------------------------------------------------------------------ properties
    @property
    def keyframe_ids(self) -> tuple[int, ...]:
        return tuple(self._keyframe_ids)

    @property
    def num_keyframes(self) -> int:
        return len(self._keyframe_ids)

    @property
    def length(self) -> int:
        """Cached tokens per layer (num_keyframes * tokens_per_frame)."""
        return self.num_keyframes * self.tokens_per_frame

    @property
    def capacity(self) -> int:
        """Tokens each layer buffer can hold (cached + scratch)."""
        return int(self._keys[0].shape[2])

    @property
    def nbytes(self) -> int:
        """Bytes of the cached K/V (what a map file stores), excluding spare capacity."""
        return self.length * self.layout.bytes_per_token(self.dtype)

    @property
    def allocated_nbytes(self) -> int:
        return self.capacity * self.layout.bytes_per_token(self.dtype)

    def bytes_per_keyframe(self) -> int:
        return self.tokens_per_frame * self.layout.bytes_per_token(self.dtype)

    def keys(self, layer: int) -> torch.Tensor:
        """View [1, H, length, D] of layer ``layer``'s cached keys (ordinal among global layers)."""
        return self._keys[layer][:, :, : self.length]

    def values(self, layer: int) -> torch.Tensor:
        return self._values[layer][:, :, : self.length]

    # ------------------------------------------------------------------ model-facing
    def ensure_capacity(self, tokens: int) -> None:
        """Make every buffer hold at least ``tokens`` tokens (grows x1.5+, keeps the content)."""
        if tokens <= self.capacity:
            return
        new_capacity = max(tokens, int(self.capacity * 1.5) + self.tokens_per_frame)
        length = self.length
        for store in (self._keys, self._values):
            for i, old in enumerate(store):
                shape = (1, self.layout.num_heads, new_capacity, self.layout.head_dim)
                new = torch.empty(shape, dtype=self.dtype, device=self.device)
                new[:, :, :length].copy_(old[:, :, :length])
                store[i] = new

    def buffers(self, layer: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The full-capacity K and V buffers of a layer; tokens past ``length`` are scratch."""
        return self._keys[layer], self._values[layer]

    # ------------------------------------------------------------------ editing
    def append_keyframe(
        self,
        keys: Sequence[torch.Tensor],
        values: Sequence[torch.Tensor],
        keyframe_id: int,
    ) -> None:
        """Append one keyframe's K/V ([1 or none, H, T, D] per layer) into the spare capacity."""
        if keyframe_id in self._keyframe_ids:
            raise CacheError(f"keyframe {keyframe_id} is already in the cache")
        if len(keys) != self.layout.num_layers or len(values) != self.layout.num_layers:
            raise CacheError(f"expected {self.layout.num_layers} layers of K and V")
        start, stop = self.length, self.length + self.tokens_per_frame
        expected = (1, self.layout.num_heads, self.tokens_per_frame, self.layout.head_dim)
        for k, v in zip(keys, values, strict=True):
            for t in (k, v):
                shape = tuple(t.shape) if t.dim() == 4 else (1, *t.shape)
                if shape != expected:
                    raise CacheError(f"keyframe K/V shape {shape} does not match {expected}")
        with self.lock:
            self.ensure_capacity(stop + self.tokens_per_frame)
            for i, (k, v) in enumerate(zip(keys, values, strict=True)):
                self._keys[i][:, :, start:stop].copy_(k.reshape(expected))
                self._values[i][:, :, start:stop].copy_(v.reshape(expected))
            self._keyframe_ids.append(int(keyframe_id))

    def relabel_keyframes(self, keyframe_ids: Sequence[int]) -> None:
        """Rename the cached keyframes, in cache order (a backend numbers a mapping pass 0..N-1;
        the tracker gives them its session-wide keyframe ids). The K/V are not touched."""
        ids = [int(i) for i in keyframe_ids]
        if len(ids) != self.num_keyframes or len(set(ids)) != len(ids):
            raise CacheError(
                f"need {self.num_keyframes} distinct keyframe ids, got {list(keyframe_ids)}"
            )
        with self.lock:
            self._keyframe_ids = ids

    def drop_keyframes(self, keyframe_ids: Sequence[int]) -> None:
        """Remove keyframes, compacting the buffers in place (order of the rest is kept)."""
        unknown = set(keyframe_ids) - set(self._keyframe_ids)
        if unknown:
            raise CacheError(f"unknown keyframe ids {sorted(unknown)}")
        keep = [pos for pos, kf in enumerate(self._keyframe_ids) if kf not in set(keyframe_ids)]
        T = self.tokens_per_frame
        index = torch.cat([torch.arange(p * T, (p + 1) * T) for p in keep]) if keep else None
        with self.lock:
            for store in (self._keys, self._values):
                for buf in store:
                    if index is not None:
                        kept = buf.index_select(2, index.to(buf.device))
                        buf[:, :, : kept.shape[2]].copy_(kept)
            self._keyframe_ids = [self._keyframe_ids[p] for p in keep]

    def clone(self) -> KVCache:
        """A deep copy of the cached part (no shared storage)."""
        out = KVCache(
            self.layout,
            self.tokens_per_frame,
            dtype=self.dtype,
            device=self.device,
            capacity_frames=self.capacity // self.tokens_per_frame,
        )
        for i in range(self.layout.num_layers):
            out._keys[i][:, :, : self.length].copy_(self.keys(i))
            out._values[i][:, :, : self.length].copy_(self.values(i))
        out._keyframe_ids = list(self._keyframe_ids)
        return out

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> KVCache:
        """A copy in another dtype and/or on another device."""
        dtype = dtype or self.dtype
        out = KVCache(
            self.layout,
            self.tokens_per_frame,
            dtype=dtype,
            device=device or self.device,
            capacity_frames=self.capacity // self.tokens_per_frame,
        )
        for i in range(self.layout.num_layers):
            out._keys[i][:, :, : self.length].copy_(self.keys(i))
            out._values[i][:, :, : self.length].copy_(self.values(i))
        out._keyframe_ids = list(self._keyframe_ids)
        return out

    def equals(self, other: KVCache) -> bool:
        """Bit-identical cached content, layout, dtype and keyframe ids."""
        if (
            self.layout != other.layout
            or self.tokens_per_frame != other.tokens_per_frame
            or self.dtype != other.dtype
            or self.keyframe_ids != other.keyframe_ids
        ):
            return False
        return all(
            torch.equal(self.keys(i), other.keys(i)) and torch.equal(self.values(i), other.values(i))
            for i in range(self.layout.num_layers)
        )

    def __repr__(self) -> str:
        return (
            f"KVCache(keyframes={self.num_keyframes}, layers={self.layout.num_layers}, "
            f"heads={self.layout.num_heads}, head_dim={self.layout.head_dim}, "
            f"tokens_per_frame={self.tokens_per_frame}, dtype={self.dtype}, "
            f"bytes={self.nbytes})"
        )

"""``KVCache``: the keys and values of every keyframe token, per global-attention layer.

This is KV-Tracker's map in tensor form. For each global layer ``i`` the cache holds
``K_i, V_i`` of shape [1, heads, length, head_dim] where ``length = num_keyframes * tokens_per_frame``
and tokens run keyframe by keyframe. K is stored exactly as it enters the attention (after
qk-norm and RoPE), so a tracking pass only has to attend to it.

Why preallocated buffers: the official code grows the cache with ``torch.cat`` in all layers for
every tracked frame, a copy of the whole cache per step that grows with the map (figures:
``benchmarks/README.md#figures-behind-the-code``). Here every layer owns
one buffer with spare capacity: a tracking pass writes its own K/V into the scratch region right
after ``length`` and attends over ``[:length + query_tokens]`` — a copy of the query's tokens only.
Appending a keyframe writes into the spare capacity; the buffer grows geometrically when full.

Storage (``kv_storage``): dense buffers in the compute dtype, or — ``storage="int8"`` or
``"float8_e4m3fn"`` — quantised data with a scale per token and head, which ``buffers(layer)`` dequantises
one layer at a time into a work pair in the compute dtype (scratch region included). ``dtype`` is
always the compute dtype (what a model reads); ``storage`` names what is kept at rest.

Pruned caches (``cache/pruning.py``): a layer may keep only some of its keyframes' tokens. Each
layer then has its own length (``layer_length``) and remembers which tokens it kept
(``kept_tokens``: indices into the unpruned keyframe-major token axis, ``num_keyframes * T``).
K is stored after RoPE, so dropping a token never needs re-rotation; a tracking pass writes its
scratch right after each layer's own length. ``length`` is then the longest layer's.

Concurrency: the scratch region is shared, so one tracking pass at a time per cache; callers hold
``cache.lock`` around a pass (backends do). Different caches (e.g. the previous map and a map being
rebuilt on a worker thread) are fully independent.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence

import torch

from kvtracker_sdk.cache.kv_storage import LayerStore, make_store
from kvtracker_sdk.cache.quantization import QUANTIZED_STORAGES, storage_name
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
        storage: str | None = None,
    ) -> None:
        """``storage``: None (dense in ``dtype``) or ``"int8"`` / ``"float8_e4m3fn"``."""
        if tokens_per_frame <= 0:
            raise CacheError(f"tokens_per_frame must be > 0, got {tokens_per_frame}")
        self.layout = layout
        self.tokens_per_frame = int(tokens_per_frame)
        self.lock = threading.RLock()
        self._keyframe_ids: list[int] = []
        # per-layer int64 [length_i] indices of the kept tokens; None = every token (unpruned)
        self._kept: list[torch.Tensor] | None = None
        capacity = max(1, capacity_frames) * self.tokens_per_frame
        self._store: LayerStore = make_store(
            layout,
            capacity,
            dtype=dtype,
            device=torch.device(device),
            storage=None if storage is None else storage_name(storage),
        )

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
        storage: str | None = None,
        kept_tokens: Sequence[torch.Tensor] | None = None,
    ) -> KVCache:
        """Wrap the per-layer K/V of a mapping pass ([1 or none, H, N*T, D] each); ``storage``
        ``"int8"`` / ``"float8_e4m3fn"`` quantises them (one layer at a time).

        A pruned cache passes ``kept_tokens`` (per layer, int64 [L_i] increasing indices into
        the N*T unpruned tokens); layer i's K/V are then [1 or none, H, L_i, D]."""
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
            storage=storage,
        )
        cache._keyframe_ids = [int(i) for i in keyframe_ids]
        if kept_tokens is not None:
            cache._set_kept(kept_tokens)
        for i, (k, v) in enumerate(zip(keys, values, strict=True)):
            k4 = k if k.dim() == 4 else k.unsqueeze(0)
            v4 = v if v.dim() == 4 else v.unsqueeze(0)
            expected = (1, layout.num_heads, cache.layer_length(i), layout.head_dim)
            if tuple(k4.shape) != expected or tuple(v4.shape) != expected:
                raise CacheError(
                    f"layer {i}: K {tuple(k4.shape)} / V {tuple(v4.shape)} do not match {expected}"
                )
            cache._store.write(i, 0, k4, v4)
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
        storage: str | None = None,
        kept_tokens: Sequence[torch.Tensor] | None = None,
    ) -> KVCache:
        """A CPU cache listing ``keyframe_ids`` whose K/V are not written yet: the caller fills
        ``stored_parts(i)`` next (a map loader reads a file straight into place, without an
        intermediate copy). ``kept_tokens``: as in ``from_layers``."""
        ids = [int(i) for i in keyframe_ids]
        if len(set(ids)) != len(ids):
            raise CacheError(f"keyframe ids must be distinct, got {ids}")
        cache = cls(
            layout,
            tokens_per_frame,
            dtype=dtype,
            capacity_frames=len(ids) + max(1, spare_frames),
            storage=storage,
        )
        cache._keyframe_ids = ids
        if kept_tokens is not None:
            cache._set_kept(kept_tokens)
        return cache

    def _set_kept(self, kept_tokens: Sequence[torch.Tensor]) -> None:
        """Check and store per-layer kept indices (increasing, within the unpruned tokens)."""
        if len(kept_tokens) != self.layout.num_layers:
            raise CacheError(
                f"expected kept tokens of {self.layout.num_layers} layers, got {len(kept_tokens)}"
            )
        full = self.num_keyframes * self.tokens_per_frame
        kept = []
        for layer, index in enumerate(kept_tokens):
            index = torch.as_tensor(index, dtype=torch.int64).reshape(-1).cpu()
            if index.numel() and (
                int(index[0]) < 0 or int(index[-1]) >= full or not bool((index.diff() > 0).all())
            ):
                raise CacheError(
                    f"layer {layer}: kept token indices must increase within [0, {full})"
                )
            kept.append(index)
        self.ensure_capacity(max(len(k) for k in kept) + self.tokens_per_frame)
        self._kept = kept

    # ------------------------------------------------------------------ properties
    @property
    def dtype(self) -> torch.dtype:
        """The compute dtype: of ``keys``, ``values`` and ``buffers`` (a model's K/V dtype)."""
        return self._store.dtype

    @property
    def device(self) -> torch.device:
        return self._store.device

    @property
    def storage(self) -> str:
        """What is kept at rest: the dtype name of a dense cache, ``"int8"`` or
        ``"float8_e4m3fn"`` for a quantised one."""
        return self._store.storage

    @property
    def quantized(self) -> bool:
        return self.storage != str(self.dtype).removeprefix("torch.")

    @property
    def keyframe_ids(self) -> tuple[int, ...]:
        return tuple(self._keyframe_ids)

    @property
    def num_keyframes(self) -> int:
        return len(self._keyframe_ids)

    @property
    def length(self) -> int:
        """Cached tokens of the longest layer (num_keyframes * tokens_per_frame unless pruned):
        scratch past it is free in every layer."""
        if self._kept is None:
            return self.num_keyframes * self.tokens_per_frame
        return max(len(k) for k in self._kept)

    def layer_length(self, layer: int) -> int:
        """Cached tokens of layer ``layer`` (ordinal among global layers)."""
        if self._kept is None:
            return self.num_keyframes * self.tokens_per_frame
        return len(self._kept[layer])

    @property
    def pruned(self) -> bool:
        """Some layer keeps fewer than all of its keyframes' tokens."""
        return self._kept is not None

    def kept_tokens(self, layer: int) -> torch.Tensor:
        """int64 [layer_length] indices of layer ``layer``'s cached tokens in the unpruned
        keyframe-major token axis (``arange(N*T)`` for an unpruned cache)."""
        if self._kept is None:
            return torch.arange(self.num_keyframes * self.tokens_per_frame)
        return self._kept[layer].clone()

    @property
    def capacity(self) -> int:
        """Tokens each layer buffer can hold (cached + scratch)."""
        return self._store.capacity

    @property
    def nbytes(self) -> int:
        """Bytes of the cached K/V at rest (what a map file stores; quantised: data + scales),
        excluding spare capacity."""
        per_layer_token = self._store.bytes_per_token() // self.layout.num_layers
        return sum(self._lengths()) * per_layer_token

    @property
    def allocated_nbytes(self) -> int:
        """Bytes held: every buffer at full capacity (quantised: plus the one-layer work pair)."""
        return self._store.allocated_nbytes()

    def bytes_per_keyframe(self) -> int:
        """A keyframe's K/V bytes; in a pruned cache the mean over its keyframes (what a keyframe
        budget in bytes should count)."""
        if self._kept is None or not self.num_keyframes:
            return self.tokens_per_frame * self._store.bytes_per_token()
        return self.nbytes // self.num_keyframes

    def keys(self, layer: int) -> torch.Tensor:
        """[1, H, length, D] cached keys of layer ``layer`` (ordinal among global layers) in the
        compute dtype: a view for a dense cache, a dequantised copy for a quantised one."""
        return self._store.read(layer, self.layer_length(layer))[0]

    def values(self, layer: int) -> torch.Tensor:
        return self._store.read(layer, self.layer_length(layer))[1]

    def stored_parts(self, layer: int) -> dict[str, torch.Tensor]:
        """Views of what layer ``layer`` keeps at rest for the cached tokens: ``key``/``value``
        [1, H, length, D] (quantised: their data, plus ``key_scale``/``value_scale``
        [1, H, length, 1] float8 e5m2)."""
        return self._store.parts(layer, self.layer_length(layer))

    # ------------------------------------------------------------------ model-facing
    def ensure_capacity(self, tokens: int) -> None:
        """Make every buffer hold at least ``tokens`` tokens (grows x1.5+, keeps the content)."""
        if tokens <= self.capacity:
            return
        new_capacity = max(tokens, int(self.capacity * 1.5) + self.tokens_per_frame)
        self._store.grow(new_capacity, self._lengths())

    def buffers(self, layer: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The full-capacity K and V buffers of a layer; tokens past ``length`` are scratch.

        Quantised: one work pair shared by all layers, refilled with this layer's dequantised
        tokens by every call (valid until the next call)."""
        return self._store.buffers(layer, self.layer_length(layer))

    def peek_buffers(self, layer: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The tensors ``buffers(layer)`` returns, without filling them (shape/dtype checks)."""
        return self._store.peek_buffers(layer)

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
        T = self.tokens_per_frame
        expected = (1, self.layout.num_heads, T, self.layout.head_dim)
        for k, v in zip(keys, values, strict=True):
            for t in (k, v):
                shape = tuple(t.shape) if t.dim() == 4 else (1, *t.shape)
                if shape != expected:
                    raise CacheError(f"keyframe K/V shape {shape} does not match {expected}")
        with self.lock:
            self.ensure_capacity(self.length + 2 * T)
            for i, (k, v) in enumerate(zip(keys, values, strict=True)):
                self._store.write(i, self.layer_length(i), k.reshape(expected), v.reshape(expected))
            self._extend_kept()
            self._keyframe_ids.append(int(keyframe_id))

    def _extend_kept(self) -> None:
        """A keyframe of T tokens was appended to every layer: its tokens are all kept."""
        if self._kept is not None:
            full, T = self.num_keyframes * self.tokens_per_frame, self.tokens_per_frame
            self._kept = [torch.cat((k, torch.arange(full, full + T))) for k in self._kept]

    def adopt_scratch(self, keyframe_id: int) -> None:
        """Make the scratch tokens of the last one-frame tracking pass a cached keyframe.

        A tracking pass of one frame leaves its own K/V (T tokens) right after each layer's
        length; adopting them appends that frame as keyframe ``keyframe_id`` without another
        pass (incremental keyframes, ``tracking/mapping/map_insertion.py``). The caller must hold
        ``lock`` from the pass to this call (another pass would overwrite the scratch). Dense
        caches only: a quantised cache's pass writes its scratch into one shared work pair.
        """
        if self.quantized:
            raise CacheError("a quantised cache keeps no per-layer scratch to adopt")
        if keyframe_id in self._keyframe_ids:
            raise CacheError(f"keyframe {keyframe_id} is already in the cache")
        if self.length + self.tokens_per_frame > self.capacity:
            raise CacheError("the cache has no scratch of a whole frame to adopt")
        with self.lock:
            self._extend_kept()
            self._keyframe_ids.append(int(keyframe_id))
            self.ensure_capacity(self.length + self.tokens_per_frame)  # scratch for the next pass

    def keep_tokens(self, kept: Sequence[torch.Tensor]) -> None:
        """Prune in place: layer i keeps only its cached tokens ``kept[i]`` (int64, increasing
        positions in ``[0, layer_length(i))``), compacted to the front of its storage."""
        if len(kept) != self.layout.num_layers:
            raise CacheError(f"expected kept tokens of {self.layout.num_layers} layers")
        with self.lock:
            positions = []
            for i, index in enumerate(kept):
                index = torch.as_tensor(index, dtype=torch.int64).reshape(-1).cpu()
                length = self.layer_length(i)
                if index.numel() and (
                    int(index[0]) < 0
                    or int(index[-1]) >= length
                    or not bool((index.diff() > 0).all())
                ):
                    raise CacheError(f"layer {i}: kept positions must increase within [0, {length})")
                positions.append(index)
            new_kept = [self.kept_tokens(i)[index] for i, index in enumerate(positions)]
            for i, index in enumerate(positions):
                self._store.keep(i, index)
            self._kept = new_kept

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
        # new token index of each old keyframe position's first token (-1: dropped)
        new_start = torch.full((max(1, self.num_keyframes),), -1, dtype=torch.int64)
        new_start[keep] = torch.arange(len(keep), dtype=torch.int64) * T
        with self.lock:
            kept = []
            for layer in range(self.layout.num_layers):
                tokens = self.kept_tokens(layer)
                new_tokens = new_start[tokens // T]
                survive = new_tokens >= 0
                kept.append(new_tokens[survive] + tokens[survive] % T)
                self._store.keep(layer, survive.nonzero().reshape(-1))
            self._keyframe_ids = [self._keyframe_ids[p] for p in keep]
            if self._kept is not None:
                self._kept = kept

    def clone(self) -> KVCache:
        """A deep copy of the cached part (no shared storage; quantised data stay quantised)."""
        return self._copy(self._store.copy(self._lengths()))

    def to(
        self,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
        *,
        storage: str | None = None,
    ) -> KVCache:
        """A copy in another compute dtype, on another device and/or in another storage.

        A quantised cache keeps its data bit for bit when only ``dtype``/``device`` change;
        ``storage`` ``"int8"`` / ``"float8_e4m3fn"`` quantises, a dtype name (e.g.
        ``"float32"``) makes a dense cache of that dtype."""
        target = torch.device(device) if device is not None else None
        wanted = storage_name(storage) if storage is not None else None
        if wanted is None and self.quantized:
            wanted = self.storage  # a dtype change keeps the quantised data
        if wanted in QUANTIZED_STORAGES:
            if wanted == self.storage:
                return self._copy(self._store.copy(self._lengths(), dtype=dtype, device=target))
            compute = dtype or self.dtype
        else:
            compute = getattr(torch, wanted) if wanted is not None else (dtype or self.dtype)
            if dtype is not None and dtype != compute:
                raise CacheError(f"a dense cache stores its compute dtype: {dtype} vs {wanted}")
            if not self.quantized:
                return self._copy(self._store.copy(self._lengths(), dtype=compute, device=target))
        store = make_store(
            self.layout,
            self.capacity,
            dtype=compute,
            device=target or self.device,
            storage=wanted if wanted in QUANTIZED_STORAGES else None,
        )
        for layer in range(self.layout.num_layers):  # one layer's full-precision copy at a time
            store.write(layer, 0, *self._store.read(layer, self.layer_length(layer)))
        return self._copy(store)

    def _lengths(self) -> list[int]:
        """Cached tokens of each layer (the store's operations take per-layer lengths)."""
        return [self.layer_length(i) for i in range(self.layout.num_layers)]

    def _copy(self, store: LayerStore) -> KVCache:
        out = KVCache.__new__(KVCache)
        out.layout, out.tokens_per_frame = self.layout, self.tokens_per_frame
        out.lock = threading.RLock()
        out._keyframe_ids = list(self._keyframe_ids)
        out._kept = None if self._kept is None else [k.clone() for k in self._kept]
        out._store = store
        return out

    def equals(self, other: KVCache) -> bool:
        """Bit-identical content at rest, layout, dtype, storage and keyframe ids."""
        if (
            self.layout != other.layout
            or self.tokens_per_frame != other.tokens_per_frame
            or self.dtype != other.dtype
            or self.storage != other.storage
            or self.keyframe_ids != other.keyframe_ids
            or self.pruned != other.pruned
        ):
            return False
        if not all(
            torch.equal(self.kept_tokens(i), other.kept_tokens(i))
            for i in range(self.layout.num_layers)
        ):
            return False
        for layer in range(self.layout.num_layers):
            mine, theirs = self.stored_parts(layer), other.stored_parts(layer)
            if not all(torch.equal(mine[name].view(torch.uint8), theirs[name].view(torch.uint8))
                       for name in mine):  # fmt: skip
                return False
        return True

    def __repr__(self) -> str:
        return (
            f"KVCache(keyframes={self.num_keyframes}, layers={self.layout.num_layers}, "
            f"heads={self.layout.num_heads}, head_dim={self.layout.head_dim}, "
            f"tokens_per_frame={self.tokens_per_frame}, dtype={self.dtype}, storage={self.storage}, "
            f"bytes={self.nbytes}{', pruned' if self.pruned else ''})"
        )

"""How a :class:`KVCache` holds its K/V at rest: dense buffers, or quantised data with scales.

Both stores keep, per cached layer, tokens along axis 2 of [1, heads, capacity, head_dim] and
answer the same token-level operations (write tokens, read them, grow, keep a subset), so
``KVCache`` bookkeeping (lengths, keyframe ids, the lock) does not depend on the storage.

- ``DenseLayers``: one K and one V buffer per layer in the compute dtype; ``buffers(layer)`` are
  those buffers themselves (what the cache always was).
- ``QuantizedLayers``: int8 or fp8 data plus float8 scales per token and head (``quantization``), and one
  K/V *work pair* in the compute dtype shared by all layers. ``buffers(layer)`` dequantises that
  layer's cached tokens into the work pair and returns it, scratch region included: a tracking
  pass reads the cache layer by layer and never holds a full-precision copy of the whole cache
  (one layer's worth, 1/L of it). The work pair is overwritten by the next ``buffers`` call, so
  one pass at a time (``KVCache.lock``, as for the dense scratch).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import torch

from kvtracker_sdk.cache.quantization import (
    QUANTIZED_STORAGES,
    QuantScheme,
    dequantize,
    dequantize_into,
    quantize,
)
from kvtracker_sdk.errors import CacheError
from kvtracker_sdk.models.layers.cache_layout import CacheLayout

__all__ = ["DenseLayers", "LayerStore", "QuantizedLayers", "make_store"]


class LayerStore(Protocol):
    """Per-layer token storage of a KV cache (see the module docstring)."""

    layout: CacheLayout
    dtype: torch.dtype  # compute dtype: what ``read`` and ``buffers`` return
    device: torch.device

    @property
    def storage(self) -> str: ...  # at-rest name: a dtype name, "int8" or "float8_e4m3fn"

    @property
    def capacity(self) -> int: ...

    def bytes_per_token(self) -> int: ...

    def allocated_nbytes(self) -> int: ...

    def write(self, layer: int, start: int, keys: torch.Tensor, values: torch.Tensor) -> None: ...

    def read(self, layer: int, length: int) -> tuple[torch.Tensor, torch.Tensor]: ...

    def buffers(self, layer: int, length: int) -> tuple[torch.Tensor, torch.Tensor]: ...

    def peek_buffers(self, layer: int) -> tuple[torch.Tensor, torch.Tensor]: ...

    def grow(self, capacity: int, lengths: Sequence[int]) -> None: ...

    def keep(self, layer: int, index: torch.Tensor) -> None: ...

    def parts(self, layer: int, length: int) -> dict[str, torch.Tensor]: ...

    def copy(
        self,
        lengths: Sequence[int],
        *,
        dtype: torch.dtype | None = None,
        device: torch.device | None = None,
    ) -> LayerStore: ...


def _shape(layout: CacheLayout, tokens: int, last: int | None = None) -> tuple[int, int, int, int]:
    return (1, layout.num_heads, tokens, layout.head_dim if last is None else last)


def _itemsize(dtype: torch.dtype) -> int:
    return torch.empty((), dtype=dtype).element_size()


class DenseLayers:
    """K and V of every layer in the compute dtype (the storage *is* the attention's buffer)."""

    def __init__(
        self, layout: CacheLayout, capacity: int, dtype: torch.dtype, device: torch.device
    ) -> None:
        self.layout, self.dtype, self.device = layout, dtype, device
        shape = _shape(layout, capacity)
        self.keys = [torch.empty(shape, dtype=dtype, device=device) for _ in layout.block_indices]
        self.values = [torch.empty(shape, dtype=dtype, device=device) for _ in layout.block_indices]

    @property
    def storage(self) -> str:
        return str(self.dtype).removeprefix("torch.")

    @property
    def capacity(self) -> int:
        return int(self.keys[0].shape[2])

    def bytes_per_token(self) -> int:
        return self.layout.bytes_per_token(self.dtype)

    def allocated_nbytes(self) -> int:
        return self.capacity * self.bytes_per_token()

    def write(self, layer: int, start: int, keys: torch.Tensor, values: torch.Tensor) -> None:
        stop = start + keys.shape[2]
        self.keys[layer][:, :, start:stop].copy_(keys)
        self.values[layer][:, :, start:stop].copy_(values)

    def read(self, layer: int, length: int) -> tuple[torch.Tensor, torch.Tensor]:
        return self.keys[layer][:, :, :length], self.values[layer][:, :, :length]

    def buffers(self, layer: int, length: int) -> tuple[torch.Tensor, torch.Tensor]:
        return self.keys[layer], self.values[layer]

    def peek_buffers(self, layer: int) -> tuple[torch.Tensor, torch.Tensor]:
        return self.keys[layer], self.values[layer]

    def grow(self, capacity: int, lengths: Sequence[int]) -> None:
        """Buffers of ``capacity`` tokens, keeping layer i's first ``lengths[i]``."""
        for store in (self.keys, self.values):
            for i, old in enumerate(store):
                new = torch.empty(_shape(self.layout, capacity), dtype=self.dtype, device=self.device)
                new[:, :, : lengths[i]].copy_(old[:, :, : lengths[i]])
                store[i] = new

    def keep(self, layer: int, index: torch.Tensor) -> None:
        """Layer ``layer`` keeps the tokens at ``index`` (int64, increasing), moved to the front."""
        for buf in (self.keys[layer], self.values[layer]):
            kept = buf.index_select(2, index.to(buf.device))
            buf[:, :, : kept.shape[2]].copy_(kept)

    def parts(self, layer: int, length: int) -> dict[str, torch.Tensor]:
        keys, values = self.read(layer, length)
        return {"key": keys, "value": values}

    def copy(
        self,
        lengths: Sequence[int],
        *,
        dtype: torch.dtype | None = None,
        device: torch.device | None = None,
    ) -> DenseLayers:
        out = DenseLayers(self.layout, self.capacity, dtype or self.dtype, device or self.device)
        for layer in range(self.layout.num_layers):
            out.write(layer, 0, *self.read(layer, lengths[layer]))
        return out


class QuantizedLayers:
    """int8/fp8 K/V with per-token float8 scales at rest, dequantised one layer at a time for attention."""

    def __init__(
        self,
        layout: CacheLayout,
        capacity: int,
        scheme: QuantScheme,
        dtype: torch.dtype,
        device: torch.device,
    ) -> None:
        if not dtype.is_floating_point or dtype.itemsize < 2:
            raise CacheError(f"a quantised cache computes in a float dtype, got {dtype}")
        self.layout, self.scheme, self.dtype, self.device = layout, scheme, dtype, device
        self.data: dict[str, list[torch.Tensor]] = {}
        self.scales: dict[str, list[torch.Tensor]] = {}
        for part, axis in (("key", scheme.key_axis), ("value", scheme.value_axis)):
            if axis != "token_head":  # every token its own scales: writes touch no other token
                raise CacheError(f"QuantizedLayers stores scales per token and head, not {axis}")
            self.data[part] = [
                torch.empty(_shape(layout, capacity), dtype=scheme.data_dtype, device=device)
                for _ in layout.block_indices
            ]
            self.scales[part] = [
                torch.empty(_shape(layout, capacity, 1), dtype=scheme.scale_dtype, device=device)
                for _ in layout.block_indices
            ]
        self._work = self._new_work(capacity)

    def _new_work(self, capacity: int) -> tuple[torch.Tensor, torch.Tensor]:
        shape = _shape(self.layout, capacity)
        return (
            torch.empty(shape, dtype=self.dtype, device=self.device),
            torch.empty(shape, dtype=self.dtype, device=self.device),
        )

    @property
    def storage(self) -> str:
        return self.scheme.storage

    @property
    def capacity(self) -> int:
        return int(self.data["key"][0].shape[2])

    def bytes_per_token(self) -> int:
        per_part = self.layout.head_dim * _itemsize(self.scheme.data_dtype) + _itemsize(self.scheme.scale_dtype)
        return 2 * self.layout.num_layers * self.layout.num_heads * per_part

    def allocated_nbytes(self) -> int:
        work = 2 * self._work[0].numel() * self._work[0].element_size()
        return self.capacity * self.bytes_per_token() + work

    def write(self, layer: int, start: int, keys: torch.Tensor, values: torch.Tensor) -> None:
        stop = start + keys.shape[2]
        for part, tensor in (("key", keys), ("value", values)):
            data, scale = quantize(tensor.to(self.device), self.scheme, "token_head")
            self.data[part][layer][:, :, start:stop].copy_(data)
            self.scales[part][layer][:, :, start:stop].copy_(scale)

    def _dequantized(self, part: str, layer: int, length: int) -> torch.Tensor:
        return dequantize(
            self.data[part][layer][:, :, :length],
            self.scales[part][layer][:, :, :length],
            self.dtype,
        )

    def read(self, layer: int, length: int) -> tuple[torch.Tensor, torch.Tensor]:
        """New compute-dtype tensors of one layer's cached tokens (not views of the cache)."""
        return self._dequantized("key", layer, length), self._dequantized("value", layer, length)

    def buffers(self, layer: int, length: int) -> tuple[torch.Tensor, torch.Tensor]:
        work_keys, work_values = self._work
        for part, work in (("key", work_keys), ("value", work_values)):
            dequantize_into(
                work[:, :, :length],
                self.data[part][layer][:, :, :length],
                self.scales[part][layer][:, :, :length],
            )
        return self._work

    def peek_buffers(self, layer: int) -> tuple[torch.Tensor, torch.Tensor]:
        self.data["key"][layer]  # an IndexError for a layer the cache does not have
        return self._work  # shape, dtype and device only: nothing is dequantised

    def grow(self, capacity: int, lengths: Sequence[int]) -> None:
        for store in (*self.data.values(), *self.scales.values()):
            for i, old in enumerate(store):
                new = torch.empty(
                    (*old.shape[:2], capacity, old.shape[3]), dtype=old.dtype, device=self.device
                )
                new[:, :, : lengths[i]].copy_(old[:, :, : lengths[i]])
                store[i] = new
        self._work = self._new_work(capacity)

    def keep(self, layer: int, index: torch.Tensor) -> None:
        for store in (*self.data.values(), *self.scales.values()):
            buf = store[layer]
            kept = buf.index_select(2, index.to(buf.device))
            buf[:, :, : kept.shape[2]].copy_(kept)

    def parts(self, layer: int, length: int) -> dict[str, torch.Tensor]:
        """Views of the stored data [1, heads, length, head_dim] and scales [1, heads, length, 1]."""
        return {
            "key": self.data["key"][layer][:, :, :length],
            "key_scale": self.scales["key"][layer][:, :, :length],
            "value": self.data["value"][layer][:, :, :length],
            "value_scale": self.scales["value"][layer][:, :, :length],
        }

    def copy(
        self,
        lengths: Sequence[int],
        *,
        dtype: torch.dtype | None = None,
        device: torch.device | None = None,
    ) -> QuantizedLayers:
        """The same quantised data (bit for bit) with another compute dtype and/or device."""
        out = QuantizedLayers(
            self.layout, self.capacity, self.scheme, dtype or self.dtype, device or self.device
        )
        for layer in range(self.layout.num_layers):
            mine, theirs = self.parts(layer, lengths[layer]), out.parts(layer, lengths[layer])
            for name, tensor in mine.items():
                theirs[name].copy_(tensor)
        return out


def make_store(
    layout: CacheLayout,
    capacity: int,
    *,
    dtype: torch.dtype,
    device: torch.device,
    storage: str | None = None,
) -> DenseLayers | QuantizedLayers:
    """A store of ``capacity`` tokens computing in ``dtype``; ``storage`` None or a dtype name =
    dense in ``dtype`` (a dense store's storage *is* its dtype), else a quantised storage name."""
    if storage is None or storage not in QUANTIZED_STORAGES:
        if storage is not None and storage != str(dtype).removeprefix("torch."):
            raise CacheError(f"a dense cache stores its compute dtype {dtype}, not {storage}")
        return DenseLayers(layout, capacity, dtype, device)
    return QuantizedLayers(layout, capacity, QUANTIZED_STORAGES[storage], dtype, device)

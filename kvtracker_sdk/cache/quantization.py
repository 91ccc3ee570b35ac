"""Quantisation of cached K/V: int8 and fp8 (e4m3) with scales, and back.

A cache layer's K or V is a tensor [1, heads, tokens, head_dim]. It is stored as ``data`` of the
storage dtype plus float scales, symmetric (no zero point)::

    data  = round(x / scale)            int8: clamped to [-127, 127]; fp8: cast, |x/scale| <= 448
    x'    = data * scale                (dequantised into the compute dtype)

Scales are absmax / qmax over one token's values in one head ([1, heads, tokens, 1];
``axis="token_head"``), so tokens are independent: appending, dropping or pruning tokens never
touches the other tokens' data. On the golden Pi3 and DA3 over the 20 TUM frames
(``benchmarks/compact_maps.py``, ``kvtracker_sdk/eval/cache_deviation.py``) one scale per token
over all heads deviated more, and per-channel K scales (KIVI's choice) no less than per-token
ones, while they would need re-quantisation whenever tokens are added (figures:
``benchmarks/README.md#figures-behind-the-code``).

Scales are stored as float8 e5m2 (range 6e-5 .. 57344), **rounded up** before the data are divided
by them: the stored scale is exactly the one the data were made with, and rounding up never clips
the largest value. Why 8-bit scales: a float16 scale per token and head costs 2 bytes per
``head_dim`` values — int8 would be only 1.88x smaller than bf16 at head_dim 32 (the golden Pi3);
with 1-byte scales it is 1.94x (1.97x at head_dim 64). The deviation measured stayed within the
noise of float16 scales (both far below what the bf16 backend causes).

Why hand-written: torch's quantised tensors (``torch.quantize_per_channel``) are qint8 CPU tensors
without fp8, without 8-bit scales and without the in-place dequantisation into a preallocated
buffer that tracking needs; the math here is a few lines.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch

from kvtracker_sdk.errors import CacheError

__all__ = [
    "QUANTIZED_STORAGES",
    "STORAGE_ALIASES",
    "QuantScheme",
    "dequantize",
    "dequantize_into",
    "quantize",
    "storage_name",
]

Axis = Literal["token", "token_head", "channel"]
SCALE_DTYPE = torch.float8_e5m2


@dataclass(frozen=True)
class QuantScheme:
    """How one storage dtype quantises K and V."""

    storage: str  # storage name: "int8" | "float8_e4m3fn"
    data_dtype: torch.dtype
    qmax: float  # largest magnitude of the data type used
    key_axis: Axis  # what one scale of K spans
    value_axis: Axis  # what one scale of V spans
    scale_dtype: torch.dtype = SCALE_DTYPE

    @property
    def is_integer(self) -> bool:
        return not self.data_dtype.is_floating_point


QUANTIZED_STORAGES: dict[str, QuantScheme] = {
    "int8": QuantScheme("int8", torch.int8, 127.0, key_axis="token_head", value_axis="token_head"),
    "float8_e4m3fn": QuantScheme(
        "float8_e4m3fn",
        torch.float8_e4m3fn,
        float(torch.finfo(torch.float8_e4m3fn).max),
        key_axis="token_head",
        value_axis="token_head",
    ),
}

# short names (config files, CLI) -> storage names (torch dtype names, what map headers record)
STORAGE_ALIASES: dict[str, str] = {
    "fp32": "float32",
    "bf16": "bfloat16",
    "fp16": "float16",
    "int8": "int8",
    "fp8": "float8_e4m3fn",
}


def storage_name(name: str) -> str:
    """The storage name of ``name`` (an alias such as ``"fp8"`` or a storage name)."""
    resolved = STORAGE_ALIASES.get(name, name)
    if resolved not in {*STORAGE_ALIASES.values(), "float64"}:
        raise CacheError(
            f"unknown cache storage {name!r} (known: {sorted(STORAGE_ALIASES)} or dtype names)"
        )
    return resolved


_REDUCE_DIMS: dict[str, tuple[int, ...]] = {
    # x: [1, heads, tokens, head_dim]: the dims one scale spans
    "token": (1, 3),  # a token's values in every head -> scale [1, 1, tokens, 1]
    "token_head": (3,),  # a token's values in one head -> [1, heads, tokens, 1]
    "channel": (2,),  # a channel of one head over all tokens -> [1, heads, 1, head_dim]
}


def round_up(x: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """Positive ``x`` (float32) in ``dtype``, rounded up (never below ``x``) and clamped to
    ``dtype``'s smallest normal and largest value: a scale rounded down would clip the data."""
    info = torch.finfo(dtype)
    narrow = x.clamp(info.tiny, info.max).to(dtype)
    low = narrow.float() < x
    if bool(low.any()):  # the next representable value: positive floats order like their bits
        bits = {1: torch.uint8, 2: torch.int16}[narrow.element_size()]
        bumped = (narrow.view(bits) + 1).view(dtype)
        narrow = torch.where(low & (narrow.float() < info.max), bumped, narrow)
    return narrow


def quantize(
    x: torch.Tensor, scheme: QuantScheme, axis: Axis
) -> tuple[torch.Tensor, torch.Tensor]:
    """``x`` [1, heads, tokens, head_dim] (any float dtype) -> (data of ``scheme.data_dtype``,
    scales of ``scheme.scale_dtype``: [1, heads, tokens, 1] for ``axis="token_head"``)."""
    work = x.to(torch.float32, copy=True)  # never scale the caller's tensor in place
    absmax = work.abs().amax(dim=_REDUCE_DIMS[axis], keepdim=True)
    scale = round_up(absmax.div_(scheme.qmax), scheme.scale_dtype)
    scaled = work.div_(scale.float())
    if scheme.is_integer:
        data = scaled.round_().clamp_(-scheme.qmax, scheme.qmax).to(scheme.data_dtype)
    else:  # fp8: the cast rounds to nearest; |scaled| <= qmax by construction
        data = scaled.clamp_(-scheme.qmax, scheme.qmax).to(scheme.data_dtype)
    return data, scale


def dequantize_into(out: torch.Tensor, data: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """``out[...] = data * scale`` in ``out``'s dtype (no temporary of ``out``'s size)."""
    out.copy_(data)  # int8 and fp8 values are exact in bf16 and fp32
    return out.mul_(scale.to(out.dtype))  # fp8 scales do not promote


def dequantize(data: torch.Tensor, scale: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """A new tensor ``data * scale`` of ``dtype``."""
    return dequantize_into(torch.empty(data.shape, dtype=dtype, device=data.device), data, scale)

"""Writing tensors in the safetensors format to an open file handle, streamed, without a copy.

Why not ``safetensors.torch.save_file``: it writes its own temporary file (``.tmpXXXXXX`` beside
the target, mode 0600) and renames it; a process killed meanwhile leaves that file behind under
a name no cleanup can attribute to a map (each can be the size of the whole map).
``safetensors.torch.save`` avoids the file but returns the whole file as one ``bytes`` object: a
second copy of the map in memory. The format is small enough to write directly into the handle
of :func:`kvtracker_sdk.io.atomic.atomic_write`: an 8-byte little-endian header length, the JSON
header (tensor name -> dtype, shape, data offsets, plus ``__metadata__``) padded with spaces to a
multiple of 8 bytes, then each tensor's bytes, in the order safetensors itself uses (largest
element size first, then by name, so every tensor starts aligned to its element size).
Files written here read back with ``safetensors.safe_open`` (tested).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import IO

import torch

__all__ = ["write_safetensors"]

_DTYPE_CODES: dict[torch.dtype, str] = {
    torch.float64: "F64", torch.float32: "F32", torch.float16: "F16", torch.bfloat16: "BF16",
    torch.int64: "I64", torch.int32: "I32", torch.uint8: "U8", torch.bool: "BOOL",
    torch.int8: "I8", torch.float8_e4m3fn: "F8_E4M3", torch.float8_e5m2: "F8_E5M2",
    torch.uint16: "U16",
}  # fmt: skip


def _raw_bytes(tensor: torch.Tensor) -> memoryview:
    """The bytes of a contiguous CPU tensor (any dtype, bfloat16 included), without a copy."""
    return tensor.reshape(-1).view(torch.uint8).numpy().data


def write_safetensors(
    handle: IO[bytes], tensors: Mapping[str, torch.Tensor], metadata: Mapping[str, str]
) -> int:
    """Write ``tensors`` (contiguous, CPU) and ``metadata`` to ``handle``; return the bytes written."""
    order = sorted(tensors, key=lambda name: (-tensors[name].element_size(), name))
    header: dict[str, object] = {"__metadata__": dict(metadata)}
    offset = 0
    for name in order:
        tensor = tensors[name]
        if not tensor.is_contiguous() or tensor.device.type != "cpu":
            raise ValueError(f"tensor {name!r} must be contiguous and on the CPU")
        size = tensor.numel() * tensor.element_size()
        header[name] = {
            "dtype": _DTYPE_CODES[tensor.dtype],
            "shape": list(tensor.shape),
            "data_offsets": [offset, offset + size],
        }
        offset += size
    raw = json.dumps(header, separators=(",", ":")).encode("utf-8")
    raw += b" " * (-len(raw) % 8)
    handle.write(len(raw).to_bytes(8, "little"))
    handle.write(raw)
    for name in order:
        if tensors[name].numel():
            handle.write(_raw_bytes(tensors[name]))
    return 8 + len(raw) + offset

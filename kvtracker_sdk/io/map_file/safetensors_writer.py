"""Writing tensors in the safetensors format to an open file handle, streamed, without a copy.

Why not ``safetensors.torch.save_file``: it writes its own temporary file (``.tmpXXXXXX`` beside
the target, mode 0600) and renames it; a process killed meanwhile leaves that file behind under
a name no cleanup can attribute to a map (each can be the size of the whole map).
``safetensors.torch.save`` avoids the file but returns the whole file as one ``bytes`` object: a
second copy of the map in memory. The format is small enough to write directly into the handle
of :func:`kvtracker_sdk.io.files.atomic.atomic_write`: an 8-byte little-endian header length, the JSON
header (tensor name -> dtype, shape, data offsets, plus ``__metadata__``) padded with spaces to a
multiple of 8 bytes, then each tensor's bytes, in the order safetensors itself uses (largest
element size first, then by name, so every tensor starts aligned to its element size).
Files written here read back with ``safetensors.safe_open`` (tested).

``final_metadata``: metadata known only once the data is written (the map's sha256 digests,
computed while the data is written instead of in a pass before it). The header is written first
with the metadata given, and rewritten in place (``pwrite``) with the final one, which must
encode to the same length (fixed-length digests do): still one pass over the data. The data
goes out in chunks, each handed to the disk at once (``writeback``), so that the final
``fsync`` does not wait for all of it.

A tensor need not be contiguous as a whole, only row by row (``byte_pieces``): the map's K/V
are written straight from views [heads, L, X] of the cache's buffers, whose heads are
contiguous slices of a larger capacity. The file holds the same bytes as for a contiguous copy.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from typing import IO

import torch

from kvtracker_sdk.io.map_file.writeback import start_writeback

__all__ = ["byte_pieces", "write_safetensors"]

_DTYPE_CODES: dict[torch.dtype, str] = {
    torch.float64: "F64", torch.float32: "F32", torch.float16: "F16", torch.bfloat16: "BF16",
    torch.int64: "I64", torch.int32: "I32", torch.uint8: "U8", torch.bool: "BOOL",
    torch.int8: "I8", torch.float8_e4m3fn: "F8_E4M3", torch.float8_e5m2: "F8_E5M2",
    torch.uint16: "U16",
}  # fmt: skip


_CHUNK = 32 << 20  # bytes written before the kernel is asked to start writing them out


def _descriptor(handle: IO[bytes]) -> int | None:
    """The handle's file descriptor (None for in-memory handles: no writeback hints)."""
    try:
        return handle.fileno()
    except (AttributeError, OSError, ValueError):  # io.UnsupportedOperation is both
        return None


def _raw_bytes(tensor: torch.Tensor) -> memoryview:
    """The bytes of a contiguous CPU tensor (any dtype, bfloat16 included), without a copy."""
    return tensor.reshape(-1).view(torch.uint8).numpy().data


def byte_pieces(tensor: torch.Tensor) -> list[memoryview]:
    """The bytes of a CPU tensor in row-major order, without a copy: one piece if it is
    contiguous, else one per row (index of the first dimension), each of which must be.
    ``ValueError`` for anything else (no tensor the map writes)."""
    if tensor.device.type != "cpu":
        raise ValueError("the tensor must be on the CPU")
    if tensor.is_contiguous():
        return [_raw_bytes(tensor)]
    rows = tensor.unbind(0) if tensor.dim() else ()
    if not rows or not all(row.is_contiguous() for row in rows):
        raise ValueError("the tensor must be contiguous, or contiguous row by row")
    return [_raw_bytes(row) for row in rows]


def _header_bytes(header: dict[str, object], metadata: Mapping[str, str]) -> bytes:
    raw = json.dumps({**header, "__metadata__": dict(metadata)}, separators=(",", ":")).encode()
    return raw + b" " * (-len(raw) % 8)


def write_safetensors(
    handle: IO[bytes],
    tensors: Mapping[str, torch.Tensor],
    metadata: Mapping[str, str],
    *,
    final_metadata: Callable[[], Mapping[str, str]] | None = None,
) -> int:
    """Write ``tensors`` (CPU, contiguous or contiguous row by row: ``byte_pieces``) and
    ``metadata`` to ``handle`` (a file opened at its start); return the bytes written.
    ``final_metadata()``, called after the data is written, replaces ``metadata`` in the header
    (same encoded length, ``ValueError`` otherwise)."""
    order = sorted(tensors, key=lambda name: (-tensors[name].element_size(), name))
    header: dict[str, object] = {"__metadata__": {}}  # safetensors puts it first
    pieces: dict[str, list[memoryview]] = {}
    offset = 0
    for name in order:
        tensor = tensors[name]
        try:
            pieces[name] = byte_pieces(tensor)
        except ValueError as exc:
            raise ValueError(f"tensor {name!r}: {exc}") from exc
        size = tensor.numel() * tensor.element_size()
        header[name] = {
            "dtype": _DTYPE_CODES[tensor.dtype],
            "shape": list(tensor.shape),
            "data_offsets": [offset, offset + size],
        }
        offset += size
    raw = _header_bytes(header, metadata)
    handle.write(len(raw).to_bytes(8, "little"))
    handle.write(raw)
    written, fd = 8 + len(raw), _descriptor(handle)
    handed = written  # bytes up to here were handed to the disk (start_writeback)
    for name in order:
        for data in pieces[name]:
            for start in range(0, len(data), _CHUNK):
                chunk = data[start : start + _CHUNK]
                handle.write(chunk)
                written += len(chunk)
                if fd is not None and written - handed >= _CHUNK:  # the disk starts at once
                    handle.flush()
                    start_writeback(fd, handed, written - handed)
                    handed = written
    if final_metadata is not None:
        final = _header_bytes(header, final_metadata())
        if len(final) != len(raw):
            raise ValueError(f"the final header has {len(final)} bytes, the first {len(raw)}")
        end = handle.tell()
        handle.seek(8)
        handle.write(final)
        handle.seek(end)
    return 8 + len(raw) + offset

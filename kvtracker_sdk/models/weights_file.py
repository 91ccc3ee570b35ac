"""Reading a ``.safetensors`` checkpoint through one open file descriptor, never a memory map.

Why not ``safetensors.torch.load_file`` / ``safe_open``: they memory-map the file. A page of a
mapping whose file is truncated underneath (a download or a copy still being written, a file
replaced in place) raises SIGBUS, which kills the app outright instead of giving an error; and
opening a path that is a FIFO blocks forever. The map reader (``io/map_file/map_reader.py``) avoids both
the same way; this is the checkpoint's side, one layer down, for the models:

1. ``os.open`` with ``O_NONBLOCK`` (a FIFO opens at once), ``fstat`` of that descriptor: anything
   but a regular file is refused, and every later read goes through the same descriptor.
2. The header (8-byte little-endian length, then JSON: name -> dtype, shape, data offsets) is
   validated against the file's size before any tensor is allocated.
3. Each tensor is ``pread`` straight into its final buffer; a short read (the file shrank) is a
   ``ModelError``, and size and mtime are compared once more at the end.

The format is simple and stable (https://github.com/huggingface/safetensors, "Format"), so
reading it here is a few lines; writing stays with the ``safetensors`` library.
"""

from __future__ import annotations

import json
import math
import os
import stat
from typing import Any

import torch

from kvtracker_sdk.errors import ModelError
from kvtracker_sdk.positional_read import read_exactly

__all__ = ["read_safetensors", "read_safetensors_keys"]

_OPEN_FLAGS = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
_MAX_HEADER_BYTES = 100_000_000  # the library's own limit
_DTYPES: dict[str, torch.dtype] = {
    "F64": torch.float64, "F32": torch.float32, "F16": torch.float16, "BF16": torch.bfloat16,
    "I64": torch.int64, "I32": torch.int32, "I16": torch.int16, "I8": torch.int8,
    "U8": torch.uint8, "BOOL": torch.bool,
    "F8_E4M3": torch.float8_e4m3fn, "F8_E5M2": torch.float8_e5m2,
}  # fmt: skip


class _Checkpoint:
    """An open checkpoint: descriptor, the ``fstat`` taken at open, the parsed header."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.source = os.fspath(path)
        try:
            self.fd = os.open(path, _OPEN_FLAGS)
        except (OSError, ValueError) as exc:  # ValueError: a NUL byte in the path
            raise ModelError(f"cannot read checkpoint {self.source}: {exc}") from exc
        try:
            status = os.fstat(self.fd)
            if not stat.S_ISREG(status.st_mode):
                raise ModelError(f"checkpoint {self.source} is not a regular file")
            self.size, self.mtime_ns = status.st_size, status.st_mtime_ns
            self.data_start, self.entries = self._read_header()
        except BaseException:
            os.close(self.fd)
            raise

    def close(self) -> None:
        os.close(self.fd)

    def _bad(self, why: str) -> ModelError:
        return ModelError(f"{self.source} is not a readable .safetensors checkpoint: {why}")

    def read_into(self, buffer: memoryview, offset: int) -> None:
        try:
            done = read_exactly(self.fd, buffer, offset)
        except OSError as exc:
            raise ModelError(f"cannot read checkpoint {self.source}: {exc}") from exc
        if done < len(buffer):
            raise ModelError(
                f"checkpoint {self.source} ended at byte {offset + done} while being read: "
                f"it was truncated or rewritten meanwhile (it had {self.size} bytes)"
            )

    def _read_header(self) -> tuple[int, dict[str, dict[str, Any]]]:
        if self.size < 8:
            raise self._bad(f"{self.size} bytes is too short")
        prefix = bytearray(8)
        self.read_into(memoryview(prefix), 0)
        header_size = int.from_bytes(prefix, "little")
        if not 2 <= header_size <= min(_MAX_HEADER_BYTES, self.size - 8):
            raise self._bad(
                f"its first 8 bytes give a {header_size}-byte header in a {self.size}-byte file "
                "(a pickle, a zip or a truncated file?)"
            )
        raw = bytearray(header_size)
        self.read_into(memoryview(raw), 8)
        try:
            header = json.loads(raw)
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise self._bad(f"its header is not JSON ({exc})") from exc
        if not isinstance(header, dict):
            raise self._bad("its header is not a JSON object")
        header.pop("__metadata__", None)
        data_bytes = self.size - 8 - header_size
        for name, entry in header.items():
            self._check_entry(name, entry, data_bytes)
        return 8 + header_size, header

    def _check_entry(self, name: str, entry: Any, data_bytes: int) -> None:
        try:
            dtype = _DTYPES[entry["dtype"]]
            shape = [int(d) for d in entry["shape"]]
            begin, end = (int(o) for o in entry["data_offsets"])
        except (KeyError, TypeError, ValueError) as exc:
            raise self._bad(f"tensor {name!r} has a malformed entry {entry!r}") from exc
        expected = math.prod(shape) * torch.empty((), dtype=dtype).element_size()
        if min(shape, default=0) < 0 or not 0 <= begin <= end <= data_bytes:
            raise self._bad(f"tensor {name!r} lies outside the file ({begin}..{end})")
        if end - begin != expected:
            raise self._bad(f"tensor {name!r} has {end - begin} bytes, its shape needs {expected}")

    def read_tensor(self, name: str) -> torch.Tensor:
        entry = self.entries[name]
        tensor = torch.empty(entry["shape"], dtype=_DTYPES[entry["dtype"]])
        begin = int(entry["data_offsets"][0])
        if tensor.numel():
            # raw bytes of the new tensor (bool and bfloat16 included): filled in place
            raw = tensor.reshape(-1).view(torch.uint8).numpy().data
            self.read_into(raw, self.data_start + begin)
        return tensor

    def check_unchanged(self) -> None:
        now = os.fstat(self.fd)
        if (now.st_size, now.st_mtime_ns) != (self.size, self.mtime_ns):
            raise ModelError(f"checkpoint {self.source} changed while it was being read")


def read_safetensors_keys(path: str | os.PathLike[str]) -> list[str]:
    """The tensor names of a checkpoint, from its validated header (no tensor data is read)."""
    checkpoint = _Checkpoint(path)
    try:
        return list(checkpoint.entries)
    finally:
        checkpoint.close()


def read_safetensors(path: str | os.PathLike[str]) -> dict[str, torch.Tensor]:
    """Every tensor of a checkpoint, on the CPU, each in its own memory (no memory map).

    ``ModelError`` for anything that is not a complete regular ``.safetensors`` file, and for a
    file that is truncated or rewritten while being read.
    """
    checkpoint = _Checkpoint(path)
    try:
        tensors = {name: checkpoint.read_tensor(name) for name in checkpoint.entries}
        checkpoint.check_unchanged()
        return tensors
    finally:
        checkpoint.close()

"""Reading a map file through one open file descriptor, never through a memory map.

Why not ``safetensors.safe_open``: it memory-maps the file, and a page of a mapping whose file
was truncated underneath (another process rewriting the map in place) raises SIGBUS, which kills
the process outright. And a path checked with ``os.stat`` and opened afterwards may have become
a FIFO in between, whose ``open`` blocks forever. So a map is read as follows:

1. ``os.open`` with ``O_NONBLOCK`` (opening a FIFO does not wait for a writer), then ``fstat``
   on that descriptor: anything but a regular file is refused. Every later read uses the same
   descriptor, so a file renamed over the path meanwhile does not matter.
2. ``pread`` of the header, then of each tensor straight into its final buffer — the K/V into
   the ``KVCache``'s preallocated buffers, head by head — hashing each chunk as it arrives.
   A short read (the file shrank) is a ``MapCorruptedError``, and the file's size and mtime are
   compared once more at the end, so a file rewritten in place never loads silently.

This is also one copy fewer than a memory map followed by the cache's copy (see
``benchmarks/map_load.py``).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import stat
from collections.abc import Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import torch

from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.errors import CacheError, MapCorruptedError, MapFormatError, MapIOError
from kvtracker_sdk.io.map_file.map_format import MapInfo
from kvtracker_sdk.io.map_file.map_schema import MAX_HEADER_BYTES, layer_kept
from kvtracker_sdk.io.map_file.map_tensors import empty_cache, layer_tensor_names
from kvtracker_sdk.positional_read import read_exactly
from kvtracker_sdk.user_files import checked_path

__all__ = ["MapFile", "open_map_file", "read_map_tensors"]

# hashlib and pread release the GIL, so tensors are read and hashed in parallel; 4 threads
# saturate memory bandwidth on common machines.
_WORKERS = max(1, min(4, os.cpu_count() or 1))
_OPEN_FLAGS = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
_TORCH_DTYPES = {
    "U8": torch.uint8, "I64": torch.int64, "F64": torch.float64, "F32": torch.float32,
    "F16": torch.float16, "BF16": torch.bfloat16, "I8": torch.int8, "U16": torch.uint16,
    "F8_E4M3": torch.float8_e4m3fn, "F8_E5M2": torch.float8_e5m2,
}  # fmt: skip


def _bytes_of(tensor: torch.Tensor) -> memoryview:
    """The writable raw bytes of a contiguous CPU tensor (any dtype, bfloat16 included)."""
    return tensor.reshape(-1).view(torch.uint8).numpy().data


@dataclass(frozen=True)
class MapFile:
    """An open map file: its descriptor and the ``fstat`` taken when it was opened."""

    fd: int
    source: str
    size: int
    mtime_ns: int

    def read_into(self, buffer: memoryview, offset: int) -> None:
        """Fill ``buffer`` from byte ``offset``; MapCorruptedError if the file ends first."""
        try:
            done = read_exactly(self.fd, buffer, offset)
        except OSError as exc:
            raise MapIOError(f"cannot read map {self.source}: {exc}") from exc
        if done < len(buffer):
            raise MapCorruptedError(
                f"{self.source} ended at byte {offset + done} while being loaded: it was "
                f"truncated or rewritten by another process (it had {self.size} bytes)"
            )

    def read_header(self) -> bytes:
        """The raw JSON header (the bytes after the 8-byte length), checked for size only."""
        if self.size < 8:
            raise MapFormatError(
                f"{self.source} is not a kvtracker map: {self.size} bytes is too short"
            )
        prefix = bytearray(8)
        self.read_into(memoryview(prefix), 0)
        header_size = int.from_bytes(prefix, "little")
        if not 2 <= header_size <= MAX_HEADER_BYTES:
            raise MapFormatError(
                f"{self.source} is not a kvtracker map: its first 8 bytes give a header of "
                f"{header_size} bytes, outside [2, {MAX_HEADER_BYTES}] (a pickle, a zip, ...?)"
            )
        if 8 + header_size > self.size:
            raise MapCorruptedError(
                f"{self.source} is truncated inside its {header_size}-byte header"
            )
        header = bytearray(header_size)
        self.read_into(memoryview(header), 8)
        return bytes(header)

    def check_unchanged(self) -> None:
        """MapCorruptedError if the file's size or mtime changed since it was opened."""
        now = os.fstat(self.fd)
        if (now.st_size, now.st_mtime_ns) != (self.size, self.mtime_ns):
            raise MapCorruptedError(
                f"{self.source} changed while it was being loaded (another process wrote it)"
            )


@contextlib.contextmanager
def open_map_file(path: str | os.PathLike[str]) -> Iterator[MapFile]:
    """Open ``path`` once for reading (a symbolic link is followed to its target);
    MapFormatError unless that is a regular file, MapIOError for a path that is not a ``str``
    or ``os.PathLike``."""
    path = checked_path(path, MapIOError, what="map")
    source = str(path)
    try:
        fd = os.open(path, _OPEN_FLAGS)
    except (OSError, ValueError) as exc:  # ValueError: a NUL byte in the path
        raise MapIOError(f"cannot read map {source}: {exc}") from exc
    try:
        status = os.fstat(fd)
        if not stat.S_ISREG(status.st_mode):
            raise MapFormatError(f"{source} is not a regular file")
        yield MapFile(fd, source, status.st_size, status.st_mtime_ns)
    finally:
        os.close(fd)


def _read_tensor(file: MapFile, chunks: list[tuple[memoryview, int]], verify: bool) -> str | None:
    """Read ``(buffer, file offset)`` chunks in order; their joint sha256 if ``verify``."""
    digest = hashlib.sha256() if verify else None
    for buffer, offset in chunks:
        file.read_into(buffer, offset)
        if digest is not None:
            digest.update(buffer)
    return None if digest is None else digest.hexdigest()


def read_map_tensors(
    file: MapFile,
    info: MapInfo,
    offsets: Mapping[str, int],
    *,
    verify: bool,
) -> tuple[dict[str, torch.Tensor], KVCache, dict[str, str]]:
    """Read every tensor of a validated header: (keyframe tensors by name, the K/V as a CPU
    cache in the file's storage — a quantised map's data and scales stay quantised —, sha256 by
    tensor name — empty unless ``verify``).

    ``offsets`` gives each tensor's first byte in the file (header and prefix included).
    """
    layers = range(info.layout.num_layers)
    kept_names = {layer_kept(i) for i in layers} if info.layer_lengths is not None else set()
    kept_tokens = None
    if info.layer_lengths is not None:  # a pruned map: its (small) token indices come first
        kept_tokens = [torch.empty(length, dtype=torch.int64) for length in info.layer_lengths]
        for layer in layers:
            chunks = [(_bytes_of(kept_tokens[layer]), offsets[layer_kept(layer)])]
            digest = _read_tensor(file, chunks, verify)
            if verify and digest != info.tensor_sha256.get(layer_kept(layer)):
                raise MapCorruptedError(f"{file.source}: checksum mismatch in {layer_kept(layer)}")
    try:
        cache = empty_cache(info, kept_tokens)
    except CacheError as exc:
        raise MapCorruptedError(
            f"{file.source}: the kept token indices are invalid: {exc}"
        ) from exc
    jobs: dict[str, list[tuple[memoryview, int]]] = {}
    for layer in layers:
        names = layer_tensor_names(layer)
        for part, view in cache.stored_parts(layer).items():
            # the file holds [heads, L, X] (L = N*T unless pruned); each head goes to its own
            # contiguous slice [L, X] of the [1, heads, capacity, X] buffer (X: head_dim, or 1
            # for scales)
            heads = [_bytes_of(view[0, head]) for head in range(info.layout.num_heads)]
            jobs[names[part]] = [
                (chunk, offsets[names[part]] + head * len(chunk))
                for head, chunk in enumerate(heads)
            ]
    keyframe_tensors: dict[str, torch.Tensor] = {}
    for name, spec in info.tensor_schema().items():
        if name not in jobs and name not in kept_names:
            keyframe_tensors[name] = torch.empty(spec.shape, dtype=_TORCH_DTYPES[spec.dtype])
            jobs[name] = [(_bytes_of(keyframe_tensors[name]), offsets[name])]
    with ThreadPoolExecutor(max_workers=_WORKERS) as pool:
        digests = pool.map(lambda chunks: _read_tensor(file, chunks, verify), jobs.values())
        named = dict(zip(jobs, digests, strict=True))
    file.check_unchanged()
    if verify:  # the kept indices were checked above; the caller's check must not miss them
        named.update({name: info.tensor_sha256[name] for name in kept_names})
    return keyframe_tensors, cache, {k: v for k, v in named.items() if v is not None}

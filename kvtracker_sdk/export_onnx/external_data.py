"""One external-data file for all the graphs of an export, each distinct weight stored once.

Why not the exporter's own ``external_data=True``: it writes one data file per graph, and the
mapping and tracking decoders hold the same decoder weights (1.8 GB of the 3.8 GB Pi3), so an
export would carry them twice. Here every initializer of at least ``min_bytes`` goes to one
shared ``weights.bin``, deduplicated by content (the exporter folds weight transposes into new,
differently named initializers, so names cannot identify them), and each graph references its
tensors by offset. This also keeps every ``.onnx`` file far below protobuf's 2 GB limit.

Offsets of large tensors are aligned to 64 KiB so that ONNX Runtime can memory-map them.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import BinaryIO

import onnx_ir as ir

__all__ = ["SharedWeightsWriter"]

_ALIGNMENT = 64 * 1024
_ALIGN_FROM_BYTES = 1024 * 1024


class SharedWeightsWriter:
    """Appends initializers to ``folder/name`` and points the graphs at them.

    Use as a context manager; ``externalize(model)`` once per graph, then save the model with
    ``onnx_ir.save(model, path)`` (no ``external_data`` argument: the references are kept).
    """

    def __init__(self, folder: Path, name: str, *, min_bytes: int = 1024) -> None:
        self.folder = folder
        self.name = name
        self.min_bytes = min_bytes
        self._file: BinaryIO | None = None
        self._offsets: dict[bytes, int] = {}  # content digest -> offset in the file
        self.size = 0

    def __enter__(self) -> SharedWeightsWriter:
        self._file = (self.folder / self.name).open("wb")
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def externalize(self, model: ir.Model) -> int:
        """Move the model's initializers of ``min_bytes`` or more to the shared file.

        Returns the number of bytes this call added to the file (0 when every tensor was
        already stored by an earlier graph).
        """
        assert self._file is not None, "use SharedWeightsWriter as a context manager"
        before = self.size
        for value in model.graph.initializers.values():
            tensor = value.const_value
            if tensor is None or tensor.nbytes < self.min_bytes:
                continue
            data = tensor.tobytes()
            offset = self._store(data)
            value.const_value = ir.ExternalTensor(
                self.name,
                offset,
                len(data),
                tensor.dtype,
                shape=ir.Shape(tensor.shape.numpy()),
                name=value.name or tensor.name or "",
                base_dir=self.folder,
            )
        return self.size - before

    def _store(self, data: bytes) -> int:
        assert self._file is not None
        digest = hashlib.blake2b(data, digest_size=20).digest()
        if digest in self._offsets:
            return self._offsets[digest]
        if len(data) >= _ALIGN_FROM_BYTES and self.size % _ALIGNMENT:
            padding = _ALIGNMENT - self.size % _ALIGNMENT
            self._file.write(b"\0" * padding)
            self.size += padding
        offset = self.size
        self._file.write(data)
        self.size += len(data)
        self._offsets[digest] = offset
        return offset

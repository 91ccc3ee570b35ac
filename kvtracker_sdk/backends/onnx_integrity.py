"""Integrity of an ONNX export folder: the sha256 of every graph and of ``weights.bin``.

The exporter records each file's sha256 in the manifest (``OnnxManifest.sha256``); a backend
verifies them before ONNX Runtime reads a byte of the folder. Without this, a ``weights.bin``
scaled by 1.5 was served under the original fingerprint (and maps made with the real weights were
accepted with it), and a crafted graph could return any pose it liked.

Hashing the full Pi3 export (~2 GB) takes a few seconds, so a file is hashed once per process:
what was verified is remembered by (real path, device, inode, size, mtime in ns). A file replaced
or rewritten since changes one of those, and is hashed again; only files this process hashed
itself are skipped.

What this does not do: the manifest is not signed, so someone who rewrites the manifest's
digests along with the files is not detected. It guards against damaged, swapped or edited
files under an unchanged manifest, which is what a cache folder or a copied export meets.
"""

from __future__ import annotations

import hashlib
import os
import threading
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from kvtracker_sdk.errors import ModelError

__all__ = ["file_digests", "forget_verified", "verify_files"]

_CHUNK = 4 * 1024 * 1024
# hashlib releases the GIL on large buffers: graphs and weights hash in parallel
_WORKERS = max(1, min(4, os.cpu_count() or 1))
_FileKey = tuple[str, int, int, int, int]  # real path, st_dev, st_ino, st_size, st_mtime_ns
_verified: dict[_FileKey, str] = {}
_lock = threading.Lock()


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    buffer = bytearray(_CHUNK)
    view = memoryview(buffer)
    with open(path, "rb", buffering=0) as handle:
        while count := handle.readinto(buffer):
            digest.update(view[:count])
    return digest.hexdigest()


def file_digests(folder: Path, names: Iterable[str]) -> dict[str, str]:
    """Hex sha256 of each file ``folder / name`` (read in parallel)."""
    names = list(names)
    with ThreadPoolExecutor(max_workers=_WORKERS) as pool:
        return dict(zip(names, pool.map(lambda name: _sha256(folder / name), names), strict=True))


def _key(path: Path) -> _FileKey:
    status = os.stat(path)
    return (
        os.path.realpath(path),
        status.st_dev,
        status.st_ino,
        status.st_size,
        status.st_mtime_ns,
    )


def verify_files(folder: Path, expected: dict[str, str]) -> None:
    """Raise ModelError unless every ``folder / name`` has the sha256 ``expected[name]``.

    Files verified earlier by this process and unchanged since (see the module docstring) are
    not hashed again.
    """
    try:
        keys = {name: _key(folder / name) for name in expected}
    except OSError as exc:
        raise ModelError(f"{folder}: cannot read the export: {exc}") from exc
    with _lock:
        pending = [name for name, key in keys.items() if _verified.get(key) != expected[name]]
    try:
        actual = file_digests(folder, pending)
    except OSError as exc:
        raise ModelError(f"{folder}: cannot read the export: {exc}") from exc
    changed = sorted(name for name in pending if actual[name] != expected[name])
    if changed:
        raise ModelError(
            f"{folder}: {changed} changed since the export (sha256 mismatch with the manifest): "
            "the folder is damaged or was tampered with; export it again with "
            "`kvtracker export-onnx`"
        )
    with _lock:
        for name in pending:
            _verified[keys[name]] = expected[name]


def forget_verified() -> None:
    """Forget what this process verified (every folder is hashed again on its next use)."""
    with _lock:
        _verified.clear()

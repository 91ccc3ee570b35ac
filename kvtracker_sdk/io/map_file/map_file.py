"""Map files (``.kvmap``): save a :class:`KeyframeMap` atomically, read its header, load it safely.

Format: safetensors (``map_schema`` lists the tensors, ``map_format`` the header). No pickle is
ever read or written: a pickle, a zip (``torch.save``) or any other file renamed ``.kvmap`` is just
bytes that fail the header checks, and is refused without being executed.

Saving streams the file (``safetensors_writer``) into a temporary file beside the target — the
K/V straight from the cache's buffers, under its lock — while other threads hash the same
bytes (the header, written first with placeholder digests of the
same length, is rewritten in place at the end: one pass over the data), fsyncs it and
``os.replace``-s it over the target (then fsyncs the directory): the path holds the old map
or the complete new one, never half of one, even if the process dies mid-write; the temporary
file of a killed save is removed by a later save once stale (``atomic``). Loading validates
the whole header before touching tensor data, then reads every tensor through the same open descriptor (never a memory
map, see ``map_reader``) straight into its final buffer — the K/V into the cache's preallocated
buffers — and verifies every tensor's sha256.

Errors: MapFormatError (not a map / malformed header), MapVersionError (too old or too new),
MapModelMismatchError (another model, family, layout or resolution), MapCorruptedError
(checksums, truncation), MapIOError (cannot read or write the file) — all MapError.
"""

from __future__ import annotations

import contextlib
import os
import re
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from enum import Enum
from pathlib import Path
from types import MappingProxyType
from typing import Any

import torch

from kvtracker_sdk._version import __version__
from kvtracker_sdk.cache.backend_info import BackendInfo
from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.config import TrackingMode
from kvtracker_sdk.errors import BackendMismatchError, MapError, MapFormatError, MapIOError
from kvtracker_sdk.geometry.camera import Camera, IntrinsicsSource
from kvtracker_sdk.io.files.atomic import STALE_TEMP_SECONDS, atomic_write
from kvtracker_sdk.io.map_file.compatibility import (
    MapCompatibility,
    TrackerRequest,
    map_compatibility,
)
from kvtracker_sdk.io.map_file.image_codec import PNG, RAW
from kvtracker_sdk.io.map_file.map_format import (
    MapInfo,
    encode_metadata,
    gauge_problem,
    loads_strict,
    parse_header,
)
from kvtracker_sdk.io.map_file.map_reader import MapFile, open_map_file, read_map_tensors
from kvtracker_sdk.io.map_file.map_schema import (
    CACHE_DTYPES,
    FORMAT_NAME,
    FORMAT_VERSION,
    MAX_GENERATION,
)
from kvtracker_sdk.io.map_file.map_tensors import (
    check_digests,
    map_from_parts,
    map_to_tensors,
    sha256_of,
)
from kvtracker_sdk.io.map_file.safetensors_writer import write_safetensors
from kvtracker_sdk.log import get_logger

__all__ = ["LoadedMap", "MapInfo", "load_map", "read_map_info", "save_map"]

_log = get_logger(__name__)
PathLike = str | os.PathLike[str]
_PLACEHOLDER_DIGEST = "0" * 64  # a sha256 hex digest's length


@dataclass(frozen=True, eq=False)
class LoadedMap:
    """A map read from a file: the map data, its header, and the tracker config it was saved with.
    ``compatibility``: the answer for the backend (and tracker request) it was loaded for; None
    when loaded without one."""

    keyframe_map: KeyframeMap
    info: MapInfo
    compatibility: MapCompatibility | None = None

    @property
    def tracker_config_json(self) -> str:
        return self.info.tracker_config_json

    @property
    def mode(self) -> str:
        return self.info.mode


# ---------------------------------------------------------------------------------- saving
def _dtype_name(storage: str) -> str:
    name = storage
    if name not in CACHE_DTYPES:
        raise MapFormatError(
            f"cannot save map: cache dtype {name} (supported: {sorted(CACHE_DTYPES)})"
        )
    return name


def _savable_resolution(keyframe_map: KeyframeMap, backend_info: BackendInfo) -> tuple[int, int]:
    """The (H, W) the map's keyframes and cache were made at, after checking that the backend
    made the cache and that the keyframes and cache agree."""
    cache = keyframe_map.cache
    if keyframe_map.num_keyframes == 0:
        raise MapFormatError("cannot save map: it has no keyframes")
    if cache.layout != backend_info.layout:
        raise BackendMismatchError(
            f"cannot save map: cache layout {cache.layout} differs from the backend's {backend_info.layout}"
        )
    first = keyframe_map.keyframes[0].image.shape
    height, width = keyframe_map.resolution if keyframe_map.resolution != (0, 0) else first[:2]
    if cache.tokens_per_frame != backend_info.tokens_per_frame(height, width):
        raise BackendMismatchError(
            f"cannot save map: {cache.tokens_per_frame} cache tokens per frame, but the backend "
            f"makes {backend_info.tokens_per_frame(height, width)} at {height}x{width}"
        )
    keyframe_ids = keyframe_map.keyframe_ids
    if len(set(keyframe_ids)) != len(keyframe_ids) or set(keyframe_ids) != set(cache.keyframe_ids):
        raise MapFormatError(
            f"cannot save map: keyframe ids {list(keyframe_ids)} do not match the cache's "
            f"{list(cache.keyframe_ids)}"
        )
    if not 0 <= keyframe_map.generation <= MAX_GENERATION:
        raise MapFormatError(
            f"cannot save map: generation {keyframe_map.generation} is outside [0, {MAX_GENERATION}]"
        )
    if problem := gauge_problem(keyframe_map.gauge):
        raise MapFormatError(f"cannot save map: {problem}")
    return int(height), int(width)


def _saved_config(tracker_config_json: str, mode: str | Enum) -> dict[str, Any]:
    """The tracker config to store: a JSON object whose "mode" is ``mode`` (added when absent,
    refused when it says another; the header keeps the mode there only)."""
    config = loads_strict(tracker_config_json, "cannot save map: the tracker config")
    if not isinstance(config, dict):
        raise MapFormatError("cannot save map: the tracker config must be a JSON object")
    mode = str(mode.value if isinstance(mode, Enum) else mode)
    # what the loader refuses is refused here too: the SDK never writes a map it cannot load
    if mode not in {m.value for m in TrackingMode}:
        raise MapFormatError(f"cannot save map: mode {mode!r} is not one of scene, object")
    if config.setdefault("mode", mode) != mode:
        raise MapFormatError(
            f"cannot save map: mode {mode!r}, but the tracker config says {config['mode']!r}"
        )
    return config


def _saved_info(
    keyframe_map: KeyframeMap,
    backend_info: BackendInfo,
    tracker_config_json: str,
    mode: str,
    sdk_version: str,
) -> MapInfo:
    """The header of ``keyframe_map`` (checksums still empty), after checking it can be loaded."""
    cache = keyframe_map.cache
    resolution = _savable_resolution(keyframe_map, backend_info)
    config = _saved_config(tracker_config_json, mode)
    return MapInfo(
        format_version=FORMAT_VERSION,
        sdk_version=sdk_version,
        created_utc=datetime.now(timezone.utc),
        backend=backend_info,
        resolution=resolution,
        dtype=_dtype_name(cache.storage),
        tokens_per_frame=cache.tokens_per_frame,
        mode=config["mode"],
        tracker_config=MappingProxyType(config),
        keyframe_ids=keyframe_map.keyframe_ids,
        cache_keyframe_ids=cache.keyframe_ids,
        generation=keyframe_map.generation,
        gauge=keyframe_map.gauge,
        user_metadata=dict(keyframe_map.metadata),
        tensor_sha256={},
        preprocessing=keyframe_map.preprocessing,
        world=keyframe_map.world,
        layer_lengths=(
            tuple(cache.layer_length(i) for i in range(cache.layout.num_layers))
            if cache.pruned
            else None
        ),
    )


# safetensors' own temporary name (``save_file``, which earlier SDK versions saved with, wrote one
# beside the map and renamed it; a killed save left it behind)
_SAFETENSORS_TEMPORARY = re.compile(r"\.tmp[A-Za-z0-9]{6}")


def _remove_safetensors_leftovers(folder: Path) -> None:
    """Remove stale ``.tmpXXXXXX`` files in ``folder`` whose header says they are kvtracker maps
    (left by saves killed inside safetensors' ``save_file``); anything else is not ours."""
    cutoff = time.time() - STALE_TEMP_SECONDS
    with contextlib.suppress(OSError):  # best effort: the save itself has succeeded
        for entry in os.scandir(folder):
            if not _SAFETENSORS_TEMPORARY.fullmatch(entry.name):
                continue
            with contextlib.suppress(OSError, MapError):
                if entry.stat().st_mtime >= cutoff:  # a concurrent writer's: still being written
                    continue
                with open_map_file(entry.path) as file:
                    is_map = f'"format":"{FORMAT_NAME}"'.encode() in file.read_header()
                if is_map:
                    os.unlink(entry.path)


def _write_locked(
    target: Path, keyframe_map: KeyframeMap, info: MapInfo, *, compact: bool
) -> tuple[MapInfo, int]:
    """Write the map file at ``target`` atomically; the sealed header and the file size.

    The K/V are hashed and written straight from the cache's buffers, not from a snapshot copy
    (a second copy of the whole cache in new memory, which costs more than the write itself): the
    cache's lock keeps them unchanged until their bytes are in the page cache, and is released
    before the fsync, the slow part. One pass over the data: the digests are computed on another
    thread while it is written, then the header (written first with placeholders of the same
    length) is rewritten.
    """
    with contextlib.ExitStack() as locked:
        locked.enter_context(keyframe_map.cache.lock)
        tensors, encoding, image_bytes = map_to_tensors(
            keyframe_map, info.resolution, compact=compact, cache_views=True
        )
        info = replace(
            info,
            keyframe_encoding=encoding,
            image_codec=RAW if image_bytes is None else PNG,
            image_bytes=image_bytes,
            tensor_sha256=dict.fromkeys(tensors, _PLACEHOLDER_DIGEST),
        )
        try:
            with atomic_write(target, binary=True) as handle:
                with ThreadPoolExecutor(max_workers=1) as hashing:
                    digests = hashing.submit(sha256_of, tensors)

                    def sealed() -> dict[str, str]:
                        nonlocal info
                        info = replace(info, tensor_sha256=digests.result())
                        return encode_metadata(info)

                    size = write_safetensors(
                        handle, tensors, encode_metadata(info), final_metadata=sealed
                    )
                locked.close()  # the data is hashed and in the page cache: the cache may change
        except (OSError, ValueError) as exc:  # ValueError: a NUL byte in the path
            raise MapIOError(f"cannot write map {target}: {exc}") from exc
    return info, size


def save_map(
    path: PathLike,
    keyframe_map: KeyframeMap,
    *,
    backend_info: BackendInfo,
    tracker_config_json: str,
    mode: str,
    sdk_version: str = __version__,
    camera: Camera | None = None,
    camera_source: IntrinsicsSource | None = None,
    compact_keyframes: bool | None = None,
) -> MapInfo:
    """Write ``keyframe_map`` to ``path`` atomically and return the written header.

    ``backend_info`` is the backend that made the cache (its fingerprint and layout go into the
    header); ``tracker_config_json`` is the tracker's configuration as a JSON object; ``mode``
    the tracking mode ("scene", "object"); ``camera`` the session's input-image intrinsics
    (optional; ``camera_source`` says where they came from). The cache's lock is held while its
    K/V are hashed and written (not during the final ``fsync``). ``compact_keyframes`` stores the
    keyframes' masks, confidences and points compactly (``io/map_file/keyframe_codec.py``: float16
    points) and their images as PNG files when that is smaller (``io/map_file/image_codec.py``:
    lossless); None (default) does so exactly when the cache is quantised, so a dense map keeps
    its points bit for bit. If anything fails,
    ``path`` still holds its previous content and no temporary file remains.
    """
    target = Path(path)
    info = _saved_info(keyframe_map, backend_info, tracker_config_json, mode, sdk_version)
    info = replace(info, camera=camera, camera_source=camera_source if camera else None)
    if compact_keyframes is None:
        compact_keyframes = keyframe_map.cache.quantized
    info, size = _write_locked(target, keyframe_map, info, compact=compact_keyframes)
    _remove_safetensors_leftovers(target.parent)
    _log.info("map saved", path=str(target), keyframes=info.num_keyframes, bytes=size)
    return replace(info, file_size=size)


# ---------------------------------------------------------------------------------- loading
def _read_header(file: MapFile) -> tuple[MapInfo, dict[str, int]]:
    """Read and validate the header only (at most MAX_HEADER_BYTES, never tensor data)."""
    info, _, offsets = parse_header(file.read_header(), file_size=file.size, source=file.source)
    return info, offsets


def read_map_info(path: PathLike) -> MapInfo:
    """The validated header of the map at ``path``, without reading any tensor data."""
    with open_map_file(path) as file:
        return _read_header(file)[0]


def load_map(
    path: PathLike,
    *,
    expected_backend: BackendInfo | None = None,
    expected_resolution: tuple[int, int] | None = None,
    verify_checksums: bool = True,
    tracker: TrackerRequest | None = None,
) -> LoadedMap:
    """Load the map at ``path``: header checks, compatibility, read through one descriptor,
    checksums (``io.map_reader``).

    With ``expected_backend`` the map must be able to run with it (see
    :func:`~kvtracker_sdk.io.map_file.compatibility.map_compatibility`, asked with
    ``expected_resolution`` (H, W) and ``tracker`` before any tensor is read; its first refusal is
    raised) and the cache is returned in that backend's dtype (if it is a cache dtype) and on its
    device. ``verify_checksums=False`` skips hashing the tensor data (faster; the
    header and sizes are still checked).
    """
    compatibility = None
    with open_map_file(path) as file:
        info, offsets = _read_header(file)
        if expected_backend is not None:
            compatibility = map_compatibility(
                info, expected_backend, resolution=expected_resolution, tracker=tracker,
                source=str(path),
            )
            compatibility.raise_if_refused()
        tensors, cache, digests = read_map_tensors(file, info, offsets, verify=verify_checksums)
    source = file.source
    if verify_checksums:
        check_digests(digests, info.tensor_sha256, source)
    dtype, device = None, None
    if expected_backend is not None:  # hand back a cache that backend can use as is
        if expected_backend.dtype in CACHE_DTYPES:
            dtype = getattr(torch, expected_backend.dtype)
        device = expected_backend.device
    keyframe_map = map_from_parts(tensors, cache, info, source, dtype=dtype, device=device)
    _log.info("map loaded", path=source, keyframes=info.num_keyframes, verified=verify_checksums)
    return LoadedMap(keyframe_map=keyframe_map, info=info, compatibility=compatibility)

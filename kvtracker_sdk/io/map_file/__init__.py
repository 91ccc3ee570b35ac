"""The ``.kvmap`` map file: save a map atomically, read its header, load it safely.

``map_file`` saves and loads; ``compatibility`` answers whether a map can run with a backend,
a tracker configuration and a camera; ``map_format`` is the header (:class:`MapInfo`), ``map_schema``
the tensor table, ``map_tensors`` a map as tensors and back, ``keyframe_codec`` the compact
keyframe payload, ``map_reader`` reads through one file descriptor, ``safetensors_writer`` and
``writeback`` write the file.

The public names load on first access (PEP 562), so importing one module of this folder does
not import the others.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from kvtracker_sdk.io.map_file.compatibility import (
        MapCompatibility,
        TrackerRequest,
        map_compatibility,
    )
    from kvtracker_sdk.io.map_file.map_file import LoadedMap, load_map, read_map_info, save_map
    from kvtracker_sdk.io.map_file.map_format import MapInfo

_LAZY: dict[str, str] = {
    "LoadedMap": "kvtracker_sdk.io.map_file.map_file",
    "MapInfo": "kvtracker_sdk.io.map_file.map_format",
    "MapCompatibility": "kvtracker_sdk.io.map_file.compatibility",
    "TrackerRequest": "kvtracker_sdk.io.map_file.compatibility",
    "map_compatibility": "kvtracker_sdk.io.map_file.compatibility",
    "load_map": "kvtracker_sdk.io.map_file.map_file",
    "read_map_info": "kvtracker_sdk.io.map_file.map_file",
    "save_map": "kvtracker_sdk.io.map_file.map_file",
}

__all__ = [
    "LoadedMap",
    "MapCompatibility",
    "MapInfo",
    "TrackerRequest",
    "load_map",
    "map_compatibility",
    "read_map_info",
    "save_map",
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

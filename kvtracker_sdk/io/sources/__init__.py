"""Where frames come from: image folders, videos and dataset sequences (``sources``), cameras,
streams and iterables (``live_sources``), depth images beside them (``depth_frames``), camera
calibration files and datasets' published intrinsics (``camera_files``), and OpenCV's own
messages while a capture opens (``opencv_messages``).

The public names load on first access (PEP 562).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from kvtracker_sdk.io.sources.camera_files import read_camera_file
    from kvtracker_sdk.io.sources.live_sources import CaptureSource, IterableSource, PacedSource
    from kvtracker_sdk.io.sources.sources import ImageSource, SourceFrame, open_source

_LAZY: dict[str, str] = {
    "CaptureSource": "kvtracker_sdk.io.sources.live_sources",
    "ImageSource": "kvtracker_sdk.io.sources.sources",
    "IterableSource": "kvtracker_sdk.io.sources.live_sources",
    "PacedSource": "kvtracker_sdk.io.sources.live_sources",
    "SourceFrame": "kvtracker_sdk.io.sources.sources",
    "open_source": "kvtracker_sdk.io.sources.sources",
    "read_camera_file": "kvtracker_sdk.io.sources.camera_files",
}

__all__ = [
    "CaptureSource",
    "ImageSource",
    "IterableSource",
    "PacedSource",
    "SourceFrame",
    "open_source",
    "read_camera_file",
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

"""kvtracker-sdk: real-time monocular camera and object tracking with KV-cached transformers.

The names an app uses are here (``from kvtracker_sdk import Tracker, TrackerConfig, ...``);
everything else is imported from its module: every error from ``kvtracker_sdk.errors``, value
types from ``kvtracker_sdk.types``, maps from ``kvtracker_sdk.io.map_file``, exports from
``kvtracker_sdk.io.exports``, many sequences from ``kvtracker_sdk.scale`` (the API reference lists them).

``import kvtracker_sdk`` is cheap: errors, value types and configuration load eagerly; everything
that pulls in torch, onnxruntime or OpenCV loads on first attribute access (PEP 562).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from kvtracker_sdk._version import __version__
from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.errors import (
    BackendError,
    ConfigError,
    InputError,
    KVTrackerError,
    MapError,
    MissingDependencyError,
    ModelError,
    OutputError,
    SourceError,
    StateError,
)
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.threads import prefer_passive_wait
from kvtracker_sdk.types import (
    FrameResult,
    MapStatus,
    ObjectFrame,
    ObjectRegion,
    Pose,
    StateReason,
    TrackedPose,
    TrackerSnapshot,
    TrackingState,
)

# before anything loads torch (nothing above does): OpenMP reads its wait policy once
prefer_passive_wait()

if TYPE_CHECKING:  # pragma: no cover
    from kvtracker_sdk.backends.base import Backend
    from kvtracker_sdk.backends.onnx import OnnxBackend
    from kvtracker_sdk.backends.openvino import OpenVinoBackend
    from kvtracker_sdk.backends.simulated import SimulatedBackend
    from kvtracker_sdk.backends.torch_backend import TorchBackend
    from kvtracker_sdk.io.map_file.map_file import read_map_info
    from kvtracker_sdk.io.sources.camera_files import read_camera_file
    from kvtracker_sdk.tracking.facade.tracker import Tracker
    from kvtracker_sdk.tracking.object.segmenter import Segmenter

# public name -> module that defines it (loaded lazily)
_LAZY: dict[str, str] = {
    "Backend": "kvtracker_sdk.backends.base",
    "OnnxBackend": "kvtracker_sdk.backends.onnx",  # onnxruntime is imported when one is made
    "OpenVinoBackend": "kvtracker_sdk.backends.openvino",  # openvino too
    "SimulatedBackend": "kvtracker_sdk.backends.simulated",
    "TorchBackend": "kvtracker_sdk.backends.torch_backend",
    "Segmenter": "kvtracker_sdk.tracking.object.segmenter",
    "Tracker": "kvtracker_sdk.tracking.facade.tracker",
    "read_camera_file": "kvtracker_sdk.io.sources.camera_files",
    "read_map_info": "kvtracker_sdk.io.map_file.map_file",
}

__all__ = [
    "Backend",
    "BackendError",
    "Camera",
    "ConfigError",
    "FrameResult",
    "InputError",
    "KVTrackerError",
    "MapError",
    "MapStatus",
    "MissingDependencyError",
    "ModelError",
    "ObjectFrame",
    "ObjectRegion",
    "OnnxBackend",
    "OpenVinoBackend",
    "OutputError",
    "Pose",
    "Segmenter",
    "SimulatedBackend",
    "SourceError",
    "StateError",
    "StateReason",
    "TorchBackend",
    "TrackedPose",
    "Tracker",
    "TrackerConfig",
    "TrackerSnapshot",
    "TrackingState",
    "__version__",
    "read_camera_file",
    "read_map_info",
]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'kvtracker_sdk' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # cache: later lookups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(__all__)

"""kvtracker-sdk: real-time monocular camera and object tracking with KV-cached transformers.

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
    BackendMismatchError,
    BBoxError,
    CacheError,
    CheckpointMismatchError,
    CompileError,
    ConfigError,
    DepthError,
    EvaluationError,
    GravityError,
    IllegalTransitionError,
    ImageDtypeError,
    ImageShapeError,
    InputError,
    KVTrackerError,
    MapCorruptedError,
    MapError,
    MapFormatError,
    MapIOError,
    MapModelMismatchError,
    MappingFailedError,
    MapPreprocessingError,
    MapVersionError,
    MaskError,
    MissingDependencyError,
    ModelError,
    NonFiniteImageError,
    OutputError,
    ResolutionChangedError,
    SourceError,
    StateError,
    TrackingFailedError,
    TrajectoryError,
    WeightsNotFoundError,
)
from kvtracker_sdk.geometry.boxes import OrientedBox
from kvtracker_sdk.geometry.camera import Camera, IntrinsicsSource
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.threads import prefer_passive_wait
from kvtracker_sdk.types import (
    FrameResult,
    HeadSet,
    MapStatus,
    ObjectFrame,
    ObjectRegion,
    Pose,
    RegionSource,
    StateReason,
    TrackedPose,
    TrackerSnapshot,
    TrackingState,
)
from kvtracker_sdk.world import (
    GravityEstimate,
    MapWorld,
    ScaleEstimate,
    ScaleSource,
    WorldAlignment,
)

# before anything loads torch (nothing above does): OpenMP reads its wait policy once
prefer_passive_wait()

if TYPE_CHECKING:  # pragma: no cover
    from kvtracker_sdk.backends.base import Backend, BackendInfo, MapResult, TrackResult
    from kvtracker_sdk.backends.onnx import OnnxBackend
    from kvtracker_sdk.backends.openvino import OpenVinoBackend
    from kvtracker_sdk.backends.simulated import SimulatedBackend
    from kvtracker_sdk.backends.torch_backend import TorchBackend
    from kvtracker_sdk.cache.keyframe_map import Keyframe, KeyframeMap
    from kvtracker_sdk.cache.kv_cache import CacheLayout, KVCache
    from kvtracker_sdk.io.camera_files import read_camera_file
    from kvtracker_sdk.io.colmap_text import write_colmap_text
    from kvtracker_sdk.io.intrinsics import PinholeIntrinsics
    from kvtracker_sdk.io.map_file import LoadedMap, load_map, read_map_info
    from kvtracker_sdk.io.map_format import MapInfo
    from kvtracker_sdk.io.nerfstudio import write_nerfstudio
    from kvtracker_sdk.io.reconstruction import Reconstruction, reconstruction_from_map
    from kvtracker_sdk.io.ros2_bag import Ros2BagWriter, write_ros2_bag
    from kvtracker_sdk.scale.manifest import EvalManifest, load_manifest
    from kvtracker_sdk.scale.results import EvalManyResult
    from kvtracker_sdk.scale.runner import run_many
    from kvtracker_sdk.scale.service import TrackerHost
    from kvtracker_sdk.tracking.live_intake import LiveStats
    from kvtracker_sdk.tracking.segmenter import Segmenter
    from kvtracker_sdk.tracking.tracker import Tracker
    from kvtracker_sdk.viz.live_viewer import Viewer

# public name -> module that defines it (loaded lazily)
_LAZY: dict[str, str] = {
    # scale-out (layer 6): Ray is imported only by an engine or actor that needs it
    "EvalManifest": "kvtracker_sdk.scale.manifest",
    "EvalManyResult": "kvtracker_sdk.scale.results",
    "TrackerHost": "kvtracker_sdk.scale.service",
    "load_manifest": "kvtracker_sdk.scale.manifest",
    "run_many": "kvtracker_sdk.scale.runner",
    "Backend": "kvtracker_sdk.backends.base",
    "BackendInfo": "kvtracker_sdk.backends.base",
    "MapResult": "kvtracker_sdk.backends.base",
    "TrackResult": "kvtracker_sdk.backends.base",
    "CacheLayout": "kvtracker_sdk.cache.kv_cache",
    "KVCache": "kvtracker_sdk.cache.kv_cache",
    "Keyframe": "kvtracker_sdk.cache.keyframe_map",
    "KeyframeMap": "kvtracker_sdk.cache.keyframe_map",
    "LiveStats": "kvtracker_sdk.tracking.live_intake",
    "Segmenter": "kvtracker_sdk.tracking.segmenter",
    "LoadedMap": "kvtracker_sdk.io.map_file",
    "read_camera_file": "kvtracker_sdk.io.camera_files",
    "MapInfo": "kvtracker_sdk.io.map_format",
    "load_map": "kvtracker_sdk.io.map_file",
    "read_map_info": "kvtracker_sdk.io.map_file",
    "OnnxBackend": "kvtracker_sdk.backends.onnx",  # onnxruntime is imported when one is made
    "OpenVinoBackend": "kvtracker_sdk.backends.openvino",  # openvino too
    "SimulatedBackend": "kvtracker_sdk.backends.simulated",
    "TorchBackend": "kvtracker_sdk.backends.torch_backend",
    "Tracker": "kvtracker_sdk.tracking.tracker",
    # exports for other tools ([ros] for the bag, [view] for the viewer: imported when made)
    "PinholeIntrinsics": "kvtracker_sdk.io.intrinsics",
    "Reconstruction": "kvtracker_sdk.io.reconstruction",
    "Ros2BagWriter": "kvtracker_sdk.io.ros2_bag",
    "Viewer": "kvtracker_sdk.viz.live_viewer",
    "reconstruction_from_map": "kvtracker_sdk.io.reconstruction",
    "write_colmap_text": "kvtracker_sdk.io.colmap_text",
    "write_nerfstudio": "kvtracker_sdk.io.nerfstudio",
    "write_ros2_bag": "kvtracker_sdk.io.ros2_bag",
}

__all__ = [
    "BBoxError",
    "Backend",
    "BackendError",
    "BackendInfo",
    "BackendMismatchError",
    "CacheError",
    "CacheLayout",
    "Camera",
    "CheckpointMismatchError",
    "CompileError",
    "ConfigError",
    "DepthError",
    "EvalManifest",
    "EvalManyResult",
    "EvaluationError",
    "FrameResult",
    "GravityError",
    "GravityEstimate",
    "HeadSet",
    "IllegalTransitionError",
    "ImageDtypeError",
    "ImageShapeError",
    "InputError",
    "IntrinsicsSource",
    "KVCache",
    "KVTrackerError",
    "Keyframe",
    "KeyframeMap",
    "LiveStats",
    "LoadedMap",
    "MapCorruptedError",
    "MapError",
    "MapFormatError",
    "MapIOError",
    "MapInfo",
    "MapModelMismatchError",
    "MapPreprocessingError",
    "MapResult",
    "MapStatus",
    "MapVersionError",
    "MapWorld",
    "MappingFailedError",
    "MaskError",
    "MissingDependencyError",
    "ModelError",
    "NonFiniteImageError",
    "ObjectFrame",
    "ObjectRegion",
    "OnnxBackend",
    "OpenVinoBackend",
    "OrientedBox",
    "OutputError",
    "PinholeIntrinsics",
    "Pose",
    "Reconstruction",
    "RegionSource",
    "ResolutionChangedError",
    "Ros2BagWriter",
    "ScaleEstimate",
    "ScaleSource",
    "Segmenter",
    "Sim3",
    "SimulatedBackend",
    "SourceError",
    "StateError",
    "StateReason",
    "TorchBackend",
    "TrackResult",
    "TrackedPose",
    "Tracker",
    "TrackerConfig",
    "TrackerHost",
    "TrackerSnapshot",
    "TrackingFailedError",
    "TrackingState",
    "TrajectoryError",
    "Viewer",
    "WeightsNotFoundError",
    "WorldAlignment",
    "__version__",
    "load_manifest",
    "load_map",
    "read_camera_file",
    "read_map_info",
    "reconstruction_from_map",
    "run_many",
    "write_colmap_text",
    "write_nerfstudio",
    "write_ros2_bag",
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

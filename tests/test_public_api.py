"""The public surface: a pinned ``__all__``, lazy heavy imports, one exception tree."""

from __future__ import annotations

import importlib
import inspect
import json
import subprocess
import sys

import numpy as np
import pytest

import kvtracker_sdk
from kvtracker_sdk import errors


def test_all_names_resolve() -> None:
    for name in kvtracker_sdk.__all__:
        assert getattr(kvtracker_sdk, name) is not None, name


def test_every_error_derives_from_the_root() -> None:
    classes = [c for _, c in inspect.getmembers(errors, inspect.isclass) if issubclass(c, Exception)]
    assert len(classes) > 10
    for cls in classes:
        assert issubclass(cls, errors.KVTrackerError), cls


# One child answers the three questions that need a fresh interpreter (each start costs ~0.5 s
# of CPU): what a bare import loads, whether an unconfigured library logger prints, and what
# naming the graph backends loads. The report is the child's only output.
_CHILD = """
import json, sys
import kvtracker_sdk
bare = [m for m in ('torch', 'cv2', 'onnxruntime', 'openvino') if m in sys.modules]
from kvtracker_sdk.log import get_logger
get_logger('test').warning('should not print', x=1)
kvtracker_sdk.OnnxBackend; kvtracker_sdk.OpenVinoBackend
graph = [m for m in ('onnxruntime', 'openvino') if m in sys.modules]
print(json.dumps({"bare": bare, "graph": graph}))
"""


@pytest.fixture(scope="module")
def fresh_child() -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True, check=True)


def test_import_is_cheap(fresh_child: subprocess.CompletedProcess[str]) -> None:
    assert json.loads(fresh_child.stdout)["bare"] == []


def test_graph_backends_import_their_runtime_only_when_one_is_made(
    fresh_child: subprocess.CompletedProcess[str],
) -> None:
    assert json.loads(fresh_child.stdout)["graph"] == []


def test_library_is_silent_by_default(fresh_child: subprocess.CompletedProcess[str]) -> None:
    assert fresh_child.stderr == ""
    assert fresh_child.stdout.splitlines() == [fresh_child.stdout.strip()]  # the report alone


def test_pose_is_immutable_and_exposes_named_quaternions() -> None:
    T = np.eye(4)
    T[:3, 3] = [1, 2, 3]
    pose = kvtracker_sdk.Pose(T)
    T[0, 3] = 99  # the pose copied its input
    assert pose.translation.tolist() == [1, 2, 3]
    with pytest.raises(ValueError):
        pose.T_world_cam[0, 0] = 2
    np.testing.assert_allclose(pose.as_quat_xyzw(), [0, 0, 0, 1])
    np.testing.assert_allclose(pose.as_quat_wxyz(), [1, 0, 0, 0])
    np.testing.assert_allclose(pose.inverse().translation, [-1, -2, -3])


# The public surface, pinned: adding or removing a name is a deliberate, reviewed change. The
# root holds what an app uses; the rest lives in its module (MOVED_FROM_ROOT; every error in
# kvtracker_sdk.errors).
PUBLIC_API = [
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

MOVED_FROM_ROOT = {
    "BackendInfo": "kvtracker_sdk.backends.base",
    "CacheLayout": "kvtracker_sdk.cache.kv_cache",
    "EvalManifest": "kvtracker_sdk.scale.manifest",
    "EvalManyResult": "kvtracker_sdk.scale.results",
    "HeadSet": "kvtracker_sdk.types",
    "IntrinsicsSource": "kvtracker_sdk.geometry.camera",
    "KVCache": "kvtracker_sdk.cache.kv_cache",
    "Keyframe": "kvtracker_sdk.cache.keyframe_map",
    "KeyframeMap": "kvtracker_sdk.cache.keyframe_map",
    "LiveStats": "kvtracker_sdk.tracking.live.live_intake",
    "LoadedMap": "kvtracker_sdk.io.map_file",
    "MapInfo": "kvtracker_sdk.io.map_file",
    "MapResult": "kvtracker_sdk.backends.base",
    "OrientedBox": "kvtracker_sdk.geometry.boxes",
    "PinholeIntrinsics": "kvtracker_sdk.io.exports.intrinsics",
    "Reconstruction": "kvtracker_sdk.io.exports",
    "RegionSource": "kvtracker_sdk.types",
    "Ros2BagWriter": "kvtracker_sdk.io.exports",
    "Sim3": "kvtracker_sdk.geometry.sim3",
    "TrackResult": "kvtracker_sdk.backends.base",
    "TrackerHost": "kvtracker_sdk.scale.service",
    "Viewer": "kvtracker_sdk.viz.live_viewer",
    "load_manifest": "kvtracker_sdk.scale.manifest",
    "load_map": "kvtracker_sdk.io.map_file",
    "reconstruction_from_map": "kvtracker_sdk.io.exports",
    "run_many": "kvtracker_sdk.scale.runner",
    "write_colmap_text": "kvtracker_sdk.io.exports",
    "write_nerfstudio": "kvtracker_sdk.io.exports",
    "write_ros2_bag": "kvtracker_sdk.io.exports",
}


def test_public_api_is_pinned() -> None:
    assert kvtracker_sdk.__all__ == PUBLIC_API


def test_the_root_stays_small_and_every_moved_name_imports_from_its_module() -> None:
    assert len(PUBLIC_API) <= 32
    for name, module in MOVED_FROM_ROOT.items():
        assert name not in kvtracker_sdk.__all__, name
        assert getattr(importlib.import_module(module), name) is not None, (name, module)
    for name in errors.__all__:  # every error: in kvtracker_sdk.errors
        assert getattr(errors, name) is not None

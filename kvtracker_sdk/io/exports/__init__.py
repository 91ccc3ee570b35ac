"""What other tools read: a map's point cloud and keyframe trajectory (``map_export``, ``ply``),
COLMAP and nerfstudio datasets (``reconstruction``, ``run_reconstruction``, ``export_camera``,
``intrinsics``, ``colmap_text``, ``nerfstudio``), and ROS 2 bags of a session (``ros2_bag``,
``ros2_messages``, ``ros_frames``).

The public names load on first access (PEP 562).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from kvtracker_sdk.io.exports.colmap_text import write_colmap_text
    from kvtracker_sdk.io.exports.nerfstudio import write_nerfstudio
    from kvtracker_sdk.io.exports.reconstruction import Reconstruction, reconstruction_from_map
    from kvtracker_sdk.io.exports.ros2_bag import Ros2BagWriter, write_ros2_bag

_LAZY: dict[str, str] = {
    "Reconstruction": "kvtracker_sdk.io.exports.reconstruction",
    "Ros2BagWriter": "kvtracker_sdk.io.exports.ros2_bag",
    "reconstruction_from_map": "kvtracker_sdk.io.exports.reconstruction",
    "write_colmap_text": "kvtracker_sdk.io.exports.colmap_text",
    "write_nerfstudio": "kvtracker_sdk.io.exports.nerfstudio",
    "write_ros2_bag": "kvtracker_sdk.io.exports.ros2_bag",
}

__all__ = [
    "Reconstruction",
    "Ros2BagWriter",
    "reconstruction_from_map",
    "write_colmap_text",
    "write_nerfstudio",
    "write_ros2_bag",
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

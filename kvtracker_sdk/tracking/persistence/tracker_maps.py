"""The tracker's side of map files: what is saved with a map, and what a loaded map runs under.

The file itself — atomic writes, header validation, checksums, never a pickle — is
``io/map_file``'s. This module adds what only the tracker knows:

* Saving stores, beside the map, the backend that made its cache (its fingerprint decides which
  backends may load the file), the tracker configuration (JSON) and the tracking mode.
* Loading for a backend refuses a map from another model (family, config hash, weights, cache
  layout, tokenisation) with ``MapModelMismatchError`` naming both models, before any tensor is
  read, and hands back the cache in that backend's dtype and on its device (an fp32 map of the
  same weights loads into a bf16 backend).
* The configuration of a loaded map: by default the one saved with it; a ``TrackerConfig``
  replaces it; a dict changes some of its fields (``TrackerConfig.updated``). Whether the map
  can run with the backend, that configuration and the session's camera is answered by
  ``io.map_file.compatibility.map_compatibility``, the one place that answers it.

Nothing here touches a tracker: ``load_tracker_map`` returns plain data that the ``Tracker``
installs in one step, so a load that fails at any point leaves the tracker as it was.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, replace
from typing import Any

from kvtracker_sdk.backends.base import BackendInfo
from kvtracker_sdk.backends.frame_checks import reads_quantized_caches
from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.errors import StateError
from kvtracker_sdk.geometry.camera import Camera, IntrinsicsSource
from kvtracker_sdk.io.exports import map_export
from kvtracker_sdk.io.map_file.compatibility import ConfigOverride, TrackerRequest
from kvtracker_sdk.io.map_file.map_file import MapInfo, load_map, save_map
from kvtracker_sdk.log import get_logger

__all__ = [
    "ConfigOverride",
    "LoadedTrackerMap",
    "export_point_cloud",
    "export_trajectory",
    "load_tracker_map",
    "save_tracker_map",
]

_log = get_logger(__name__)
PathLike = str | os.PathLike[str]


@dataclass(frozen=True, eq=False)
class LoadedTrackerMap:
    """A saved map ready to install: the map (cache in the loading backend's dtype and device,
    keyframe poses in the saved world frame, the saved gauge), its configuration and its header."""

    keyframe_map: KeyframeMap
    config: TrackerConfig
    info: MapInfo


def _require_map(keyframe_map: KeyframeMap | None, action: str) -> KeyframeMap:
    if keyframe_map is None:
        raise StateError(
            f"cannot {action}: the tracker has no map yet (push frames until it has mapped, "
            "or load one)"
        )
    return keyframe_map


def save_tracker_map(
    path: PathLike,
    keyframe_map: KeyframeMap | None,
    backend_info: BackendInfo,
    config: TrackerConfig,
    camera: tuple[Camera, IntrinsicsSource] | None = None,
) -> MapInfo:
    """Write ``keyframe_map`` (made by ``backend_info``'s backend under ``config``) to ``path``,
    with the session's input-image intrinsics ``camera`` (and their source) if known.

    Atomic: if anything fails, ``path`` keeps its previous content. Raises StateError when there
    is no map, MapIOError when the file cannot be written.
    """
    kf_map = _require_map(keyframe_map, "save the map")
    return save_map(
        path,
        kf_map,
        backend_info=backend_info,
        tracker_config_json=json.dumps(config.to_dict(), sort_keys=True),
        mode=config.mode.value,
        camera=None if camera is None else camera[0],
        camera_source=None if camera is None else camera[1],
    )


def load_tracker_map(
    path: PathLike, backend_info: BackendInfo, config: ConfigOverride = None, *,
    backend_preprocessing: str | None = None, camera: Camera | None = None,
) -> LoadedTrackerMap:
    """Load and verify the map at ``path`` for the backend described by ``backend_info``.
    ``backend_preprocessing``: the name of the preprocessing the backend declares (known even
    when it is not registered). ``camera``: the session's intrinsics; when they differ from the
    map's saved ones a WARNING ``map_camera_mismatch`` is logged (not refused: the networks take
    no intrinsics as input, but the map's geometry was made by the saved camera).

    Whether the map can run is answered once, from its header, before any tensor is read
    (``io.map_file.compatibility.map_compatibility``); its first refusal is raised (model
    mismatch, unknown preprocessing, config errors), then those of reading the file
    (corruption, I/O).
    """
    source = str(path)
    request = TrackerRequest(config, backend_preprocessing, camera)
    loaded = load_map(path, expected_backend=backend_info, tracker=request)
    resolved = loaded.compatibility.config if loaded.compatibility is not None else None
    if resolved is None:  # unreachable: load_map raised the refusal
        raise StateError(f"{source}: no configuration was resolved for the map")
    if loaded.compatibility is not None and not loaded.compatibility.camera_agrees:
        saved, given = loaded.info.camera, camera
        _log.warning("map_camera_mismatch", path=source,
                     saved=None if saved is None else saved.undistorted().to_dict(),
                     given=None if given is None else given.undistorted().to_dict(),
                     saved_source=getattr(loaded.info.camera_source, "value", None))  # fmt: skip
    keyframe_map = loaded.keyframe_map
    if keyframe_map.cache.quantized and not reads_quantized_caches(backend_info):
        # e.g. ONNX Runtime, whose graph takes the whole cache as inputs: dequantised once here
        _log.warning("quantised map dequantised for a backend that cannot read it",
                     path=source, storage=keyframe_map.cache.storage, backend=backend_info.backend)  # fmt: skip
        keyframe_map = replace(
            keyframe_map, cache=keyframe_map.cache.to(storage=backend_info.dtype)
        )
        if resolved.cache_dtype != "backend":  # the session goes on with dense maps
            resolved = resolved.updated(cache_dtype="backend")
    return LoadedTrackerMap(keyframe_map, resolved, loaded.info)


def export_point_cloud(keyframe_map: KeyframeMap | None, path: PathLike, **options: Any) -> int:
    """The map's fused, confidence-filtered point cloud as binary PLY (world frame); returns the
    point count. ``options``: ``min_confidence``, ``use_masks``, ``voxel_size`` (see
    ``io.map_export.fused_point_cloud``). StateError without a map."""
    kf_map = _require_map(keyframe_map, "export a point cloud")
    return map_export.export_point_cloud(kf_map, path, **options)


def export_trajectory(keyframe_map: KeyframeMap | None, path: PathLike) -> int:
    """The keyframes' ``T_world_cam`` as a TUM trajectory sorted by time; returns the pose count.
    StateError without a map."""
    kf_map = _require_map(keyframe_map, "export the keyframe trajectory")
    return map_export.export_keyframe_trajectory(kf_map, path)

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
  replaces it; a dict changes some of its fields (``TrackerConfig.updated``). Either way the mode
  and the resolution side must be the map's: its keyframe images and K/V exist at one model input
  size (otherwise ``MapModelMismatchError``), and object maps hold masked keyframes (otherwise
  ``ConfigError``).

Nothing here touches a tracker: ``load_tracker_map`` returns plain data that the ``Tracker``
installs in one step, so a load that fails at any point leaves the tracker as it was.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

from kvtracker_sdk.backends.base import BackendInfo
from kvtracker_sdk.backends.frame_checks import reads_quantized_caches
from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.errors import (
    ConfigError,
    MapFormatError,
    MapModelMismatchError,
    MapVersionError,
    StateError,
)
from kvtracker_sdk.geometry.camera import Camera, IntrinsicsSource
from kvtracker_sdk.io.exports import map_export
from kvtracker_sdk.io.map_file.map_file import MapInfo, load_map, save_map
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.preprocess import PREPROCESSINGS

__all__ = [
    "ConfigOverride",
    "check_map_camera",
    "LoadedTrackerMap",
    "export_point_cloud",
    "export_trajectory",
    "load_tracker_map",
    "resolve_config",
    "save_tracker_map",
]

_log = get_logger(__name__)
PathLike = str | os.PathLike[str]
ConfigOverride = TrackerConfig | Mapping[str, Any] | None


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


def _saved_config(info: MapInfo, source: str) -> TrackerConfig:
    try:
        config = TrackerConfig.from_dict(json.loads(info.tracker_config_json))
    except ConfigError as exc:  # e.g. a map from a newer SDK with more settings
        raise MapFormatError(
            f"{source}: the tracker config saved in the map is not valid for this SDK ({exc}); "
            "pass config=TrackerConfig(...) to choose one"
        ) from exc
    if config.mode.value != info.mode:  # both come from the file: it contradicts itself
        raise MapFormatError(
            f"{source}: the header says {info.mode} mode, the saved tracker config "
            f"{config.mode.value} mode"
        )
    return config


def _fits_side(resolution: tuple[int, int], side: int, patch: int) -> bool:
    """Whether any preprocessing (``kvtracker_sdk.preprocess.sizing``) could give (H, W) at a
    resolution ``side`` — a necessary condition that holds for every pipeline, so a genuine map is
    never refused. Upper bound: at most side² pixels for Pi3's and the legacy sizing (the legacy
    one may exceed it only with a side clamped to one patch), (side + patch/2)² for DA3's longest
    side. Lower bound: Pi3's and the legacy sizing round or floor each side by less than a patch
    below the budget, so (H + patch)(W + patch) > side²; DA3's longest side is within patch/2 of
    ``side``."""
    height, width = resolution
    below = height * width <= (side + patch) ** 2 or min(height, width) <= patch
    longest = max(height, width)
    above = (height + patch) * (width + patch) > side * side or 2 * longest >= 2 * side - patch
    return below and above


def resolve_config(info: MapInfo, override: ConfigOverride, source: str) -> TrackerConfig:
    """The configuration a map saved with ``info`` runs under (see the module docstring).

    Raises ConfigError for an invalid override or another mode, MapModelMismatchError for
    another resolution side, MapFormatError if the saved config is needed but unreadable.
    """
    if isinstance(override, TrackerConfig):
        config = override
    elif override is not None and not isinstance(override, Mapping):
        raise ConfigError(f"config must be a TrackerConfig, a dict or None, not {override!r}")
    else:
        config = _saved_config(info, source)
        if override:
            config = config.updated(**override)
    if config.mode.value != info.mode:
        raise ConfigError(
            f"{source} was saved in {info.mode} mode; the tracker is configured for "
            f"{config.mode.value} mode"
        )
    saved_side = json.loads(info.tracker_config_json).get("resolution")
    if isinstance(saved_side, int) and not _fits_side(
        info.resolution, saved_side, info.backend.patch_size
    ):
        height, width = info.resolution
        raise MapFormatError(
            f"{source}: its saved tracker config has resolution {saved_side}, which cannot give "
            f"its {height}x{width} keyframes (patch {info.backend.patch_size})"
        )
    if config.resolution is None and isinstance(saved_side, int):
        config = config.updated(resolution=saved_side)  # unset: the map's
    if isinstance(saved_side, int) and saved_side != config.resolution:
        height, width = info.resolution
        raise MapModelMismatchError(
            f"{source} was built at resolution {saved_side} (model input {height}x{width}); "
            f"the tracker is configured for resolution {config.resolution}"
        )
    return config


def load_tracker_map(
    path: PathLike, backend_info: BackendInfo, config: ConfigOverride = None, *,
    backend_preprocessing: str | None = None,
) -> LoadedTrackerMap:
    """Load and verify the map at ``path`` for the backend described by ``backend_info``.
    ``backend_preprocessing``: the name of the preprocessing the backend declares (known even
    when it is not registered).

    Raises the map errors of ``io/map_file`` (format, version, model mismatch — checked before
    the tensor data is read —, corruption, I/O) and those of :func:`resolve_config`.
    """
    source = str(path)
    loaded = load_map(path, expected_backend=backend_info)
    known = loaded.info.preprocessing in PREPROCESSINGS
    if not known and loaded.info.preprocessing != backend_preprocessing:
        raise MapVersionError(
            f"{source}: its frames were prepared by {loaded.info.preprocessing!r}, which this SDK "
            f"does not know (known: {sorted(PREPROCESSINGS)}); upgrade kvtracker-sdk"
        )
    resolved = resolve_config(loaded.info, config, source)
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


def check_map_camera(info: MapInfo, given: Camera | None, source: str) -> bool:
    """Warn (log WARNING ``map_camera_mismatch``) when the intrinsics given for this session
    differ from those saved with the map; True when they agree or either is unknown.

    Differ means: another image size, a focal length off by more than 1 %, or a principal point
    off by more than 1 % of the image size. Not refused: the networks take no intrinsics as
    input, so tracking runs; but the map's geometry was made by the saved camera, so poses and
    scale are only as good as the two cameras are alike.
    """
    saved = info.camera
    if saved is None or given is None:
        return True
    given = given.undistorted()
    saved = saved.undistorted()
    same = (
        saved.size == given.size
        and abs(given.fx / saved.fx - 1.0) <= 0.01
        and abs(given.fy / saved.fy - 1.0) <= 0.01
        and abs(given.cx - saved.cx) <= 0.01 * saved.width
        and abs(given.cy - saved.cy) <= 0.01 * saved.height
    )
    if not same:
        _log.warning("map_camera_mismatch", path=source, saved=saved.to_dict(),
                     given=given.to_dict(), saved_source=getattr(info.camera_source, "value", None))
    return same


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

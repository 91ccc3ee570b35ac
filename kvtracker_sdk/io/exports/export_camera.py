"""Which camera an export (COLMAP, nerfstudio) writes for a map's keyframe images.

In order:

1. a calibration the caller gives (``kvtracker export --intrinsics`` / ``--camera``);
2. the camera stored in the map: the session's given one (``kvtracker track --camera``, or the
   dataset's published intrinsics) or the network's predicted one (DA3), which are the run's
   ``FrameResult.intrinsics``; stored for the input images, so it is undistorted and scaled to
   the keyframe images (the tracker undistorted, then resized, the whole frame);
3. only when no camera is known: one focal length fitted to the keyframes' points (or the
   tracker's own such fit, stored as ``estimated``). A fit under a tenth of the image width is
   no camera (random or broken weights give ~1 px): refused with an ``IntrinsicsError`` saying
   how to pass a calibration, unless ``force_fitted_focal``.

Object-mode maps that crop each keyframe have no single camera of their keyframe images: there
only a given calibration of the model images, or the fit, is used.
"""

from __future__ import annotations

import enum

import numpy as np

from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.errors import IntrinsicsError
from kvtracker_sdk.geometry.camera import Camera, IntrinsicsSource
from kvtracker_sdk.io.exports.intrinsics import estimate_intrinsics
from kvtracker_sdk.io.map_file.map_format import MapInfo
from kvtracker_sdk.log import get_logger

__all__ = ["MIN_FOCAL_PER_WIDTH", "CameraOrigin", "check_fitted_focal", "export_camera"]

_log = get_logger(__name__)

MIN_FOCAL_PER_WIDTH = 0.1  # a focal under W / 10 is a ~170 degree field of view: not a fit
HOW_TO_PASS = (
    "pass the calibration: `kvtracker export ... --camera FILE` (JSON/YAML, ROS CameraInfo) or "
    "`--intrinsics fx,fy,cx,cy,W,H`, or track with `kvtracker track --camera FILE` so that the "
    "map stores it; `--force-fitted-focal` exports the fit anyway"
)


class CameraOrigin(str, enum.Enum):
    """Where an export's camera came from."""

    GIVEN = "given"  # passed to the export
    MAP = "map"  # stored in the map (the session's given or predicted camera)
    FITTED = "fitted"  # fitted to the points (by the tracker, or here)


def export_camera(
    keyframe_map: KeyframeMap,
    info: MapInfo | None = None,
    *,
    given: Camera | None = None,
    min_confidence: float = 0.5,
    force_fitted_focal: bool = False,
) -> tuple[Camera, CameraOrigin]:
    """The pinhole camera of the map's keyframe images (model resolution), and its origin.

    ``given``: a calibration of the input images or of the model images (any size: it is
    undistorted and resized to the keyframes'). ``info``: the map's header, whose camera is
    used when no calibration is given. Raises IntrinsicsError for an implausible fit.
    """
    height, width = keyframe_map.resolution
    if given is not None:
        return given.undistorted().resized(width, height), CameraOrigin.GIVEN
    stored = _stored_camera(info)
    if stored is not None:
        camera, source = stored
        scaled = camera.undistorted().resized(width, height)
        if source is not IntrinsicsSource.ESTIMATED:
            return scaled, CameraOrigin.MAP
        return check_fitted_focal(scaled, force=force_fitted_focal), CameraOrigin.FITTED
    fitted = estimate_intrinsics(
        np.stack([kf.local_points for kf in keyframe_map.keyframes]),
        np.stack([kf.confidence_map for kf in keyframe_map.keyframes]),
        min_confidence=min_confidence,
    )
    return check_fitted_focal(fitted, force=force_fitted_focal), CameraOrigin.FITTED


def check_fitted_focal(camera: Camera, *, force: bool = False) -> Camera:
    """``camera`` if its focal is plausible (>= width / 10), or forced (a warning); else
    IntrinsicsError saying how to pass a calibration."""
    smallest = min(camera.fx, camera.fy)
    if smallest >= MIN_FOCAL_PER_WIDTH * camera.width:
        return camera
    text = (f"no camera is known for this map and the focal length fitted to its points is "
            f"{smallest:.3g} px for {camera.width}-pixel-wide images (under a tenth of the "
            f"width: not a camera; the weights may be random or wrong)")
    if not force:
        raise IntrinsicsError(f"{text}; {HOW_TO_PASS}")
    _log.warning("implausible fitted focal exported (forced)", fx=camera.fx, width=camera.width)
    return camera


def _stored_camera(info: MapInfo | None) -> tuple[Camera, IntrinsicsSource | None] | None:
    """The map header's camera, when it describes the keyframe images up to a resize."""
    if info is None or info.camera is None:
        return None
    if _crops_keyframes(info):
        _log.info("the map's keyframes are object crops: its camera is not theirs")
        return None
    return info.camera, info.camera_source


def _crops_keyframes(info: MapInfo) -> bool:
    if info.mode != "object":
        return False
    obj = info.tracker_config.get("object")  # the header's config, parsed when it was read
    return not isinstance(obj, dict) or obj.get("preprocessing", "mask") != "mask"

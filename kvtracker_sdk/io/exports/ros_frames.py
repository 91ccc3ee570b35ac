"""The tracker's poses as a ROS TF tree (REP 103 axes, REP 105 frames), in plain numpy.

Tree: ``map -> odom -> base_link -> camera_optical_frame``.

- ``camera_optical_frame``: the tracked camera, OpenCV axes (x right, y down, z forward), as
  REP 103 prescribes for optical frames.
- ``base_link -> camera_optical_frame`` is static: ``T_base_optical``, by default the camera at
  base_link's origin looking along base_link's x (x forward, y left, z up). Configurable.
- ``map``: the tracker's world frame re-expressed in body axes: map is where base_link was when
  the world's origin camera (keyframe 0, identity) was taken, i.e. ``T_map_world =
  T_base_optical``. So ``T_map_base = T_base_optical @ T_world_cam @ T_base_optical⁻¹``, and
  with the default extrinsic a level camera gives z up in map. A **gravity-aligned** world
  (``MapWorld.gravity_aligned``: gravity readings were given) already has REP 103 axes — z up,
  x keyframe 0's viewing direction made horizontal, y left — so it *is* the map frame:
  ``T_map_world = I`` and map's z is up whatever the camera's tilt was.
- Pose jumps (REP 105): ``odom -> base_link`` is continuous. Within a *segment* (consecutive
  valid frames of one map generation) it moves with the tracked pose. At a segment start (the
  first valid frame after a relocalisation or after frames without a valid pose, and the first
  frame after a map rebuild — a rebuild's alignment can correct the pose) the relative motion
  across the gap is unknown, so odom holds still and the whole correction goes into ``map ->
  odom``, which otherwise stays constant. ``map -> odom -> base_link`` always composes to the
  tracked pose exactly.

Scale: units are the world frame's: metres when the world is metric (depth frames or a known
size, ``MapWorld.metric``), else the first mapping pass's arbitrary unit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kvtracker_sdk.errors import InputError
from kvtracker_sdk.geometry.se3 import check_rigid, invert_rigid

__all__ = [
    "DEFAULT_T_BASE_OPTICAL", "FrameNames", "OdometrySplit", "map_from_world", "map_in_world",
]

# optical z (forward) = base x, optical x (right) = -base y, optical y (down) = -base z
DEFAULT_T_BASE_OPTICAL = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


@dataclass(frozen=True)
class FrameNames:
    """The TF frame ids (REP 105 names by default)."""

    map: str = "map"
    odom: str = "odom"
    base: str = "base_link"
    camera: str = "camera_optical_frame"


def checked_extrinsic(T_base_optical: np.ndarray | None) -> np.ndarray:
    """The static ``base_link -> camera_optical_frame`` transform, validated (4x4 rigid)."""
    if T_base_optical is None:
        return DEFAULT_T_BASE_OPTICAL.copy()
    T = np.asarray(T_base_optical, dtype=np.float64)
    if T.shape != (4, 4) or not check_rigid(T, atol=1e-6):
        raise InputError("T_base_optical must be a rigid 4x4 transform (base_link <- optical)")
    return T.copy()


def map_in_world(T_base_optical: np.ndarray, *, gravity_aligned: bool = False) -> np.ndarray:
    """``T_map_world`` [4, 4]: the identity for a gravity-aligned world (already z up), else
    ``T_base_optical`` (see the module docstring)."""
    return np.eye(4) if gravity_aligned else np.array(T_base_optical, dtype=np.float64)


def map_from_world(
    T_world_cam: np.ndarray, T_base_optical: np.ndarray, *, gravity_aligned: bool = False
) -> np.ndarray:
    """``T_map_base`` [4, 4] of a tracked camera pose ``T_world_cam`` (see the module docstring)."""
    T_map_world = map_in_world(T_base_optical, gravity_aligned=gravity_aligned)
    return T_map_world @ T_world_cam @ invert_rigid(T_base_optical)


class OdometrySplit:
    """Splits ``T_map_base`` into ``T_map_odom @ T_odom_base`` with a continuous odom (REP 105)."""

    def __init__(self) -> None:
        self.T_map_odom = np.eye(4)
        self.T_odom_base: np.ndarray | None = None
        self.jumps = 0  # segment starts after the first: pose jumps moved into map -> odom

    def update(self, T_map_base: np.ndarray, *, continuous: bool) -> tuple[np.ndarray, np.ndarray]:
        """(``T_map_odom``, ``T_odom_base``) for the next valid pose; ``continuous`` is False at
        a segment start (the relative motion from the previous valid pose is not trusted)."""
        if self.T_odom_base is None:  # the very first pose: odom coincides with map
            self.T_odom_base = np.array(T_map_base, dtype=np.float64)
        elif continuous:
            self.T_odom_base = invert_rigid(self.T_map_odom) @ T_map_base
        else:  # odom holds still; the jump goes into map -> odom
            self.T_map_odom = T_map_base @ invert_rigid(self.T_odom_base)
            self.jumps += 1
        return self.T_map_odom.copy(), self.T_odom_base.copy()

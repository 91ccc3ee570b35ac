"""Plain value types shared by every layer: poses, states, per-frame results.

Pose convention everywhere in the SDK: a 4x4 ``T_world_cam`` (camera-to-world) in float64, with
OpenCV camera axes (x right, y down, z forward). Quaternions appear only through the explicitly
named ``as_quat_xyzw`` / ``as_quat_wxyz`` accessors.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

import numpy as np

from kvtracker_sdk.errors import InputError, MappingFailedError, TrackingFailedError
from kvtracker_sdk.geometry.boxes import ImageBox, OrientedBox
from kvtracker_sdk.geometry.camera import Camera, IntrinsicsSource
from kvtracker_sdk.geometry.se3 import (
    check_rigid,
    quat_wxyz_from_rotation,
    quat_xyzw_from_rotation,
)
from kvtracker_sdk.world import GravityEstimate, MapWorld, ScaleEstimate

__all__ = [
    "FrameResult",
    "HeadSet",
    "MapStatus",
    "ObjectFrame",
    "ObjectRegion",
    "Pose",
    "RegionSource",
    "StateReason",
    "TrackedPose",
    "TrackerSnapshot",
    "TrackingState",
]


class TrackingState(str, enum.Enum):
    """What the app can rely on (see the state table in ``tracking/loop/states.py``)."""

    INIT = "INIT"  # no map (new, or after reset())
    MAPPING = "MAPPING"  # the first map is being built; no localisation yet
    TRACKING = "TRACKING"  # localised against the map; pose valid
    RELOCALIZING = "RELOCALIZING"  # a map exists but the current pose is not trusted


class StateReason(str, enum.Enum):
    """Why the tracker is in its current state."""

    NONE = "NONE"
    BOOTSTRAP = "BOOTSTRAP"  # first map being built / just built
    LOW_CONFIDENCE = "LOW_CONFIDENCE"  # tracking confidence dropped for `lost_after` frames
    MAP_LOADED = "MAP_LOADED"  # a saved map was loaded; waiting for confident frames
    RELOCALIZED = "RELOCALIZED"  # confident again for `recover_after` frames
    RESET = "RESET"  # reset() was called
    TIMEOUT = "TIMEOUT"  # relocalisation timed out and the policy acted
    NEW_MAP = "NEW_MAP"  # relocalisation timed out and a new map was started
    # the map after a timeout started from a frame below the lost map's confidence floor: allowed
    # once `FLOOR_RELAXES_AFTER` attempts in a row fell short (a place the network is less sure of)
    RELAXED_FLOOR = "RELAXED_FLOOR"
    # object mode: a loaded object map's object was not found in the whole frame for
    # `object.search_frames` frames; give its mask or box with a frame that shows it
    OBJECT_NOT_FOUND = "OBJECT_NOT_FOUND"


class HeadSet(str, enum.Enum):
    """Which output heads a tracking pass computes (fewer heads, faster step)."""

    CAMERA = "camera"  # pose only: the fastest step; no confidence, so no loss detection
    CONFIDENCE = "camera+conf"  # pose and per-pixel confidence (the tracker's default)
    ALL = "all"  # pose, confidence and local points


@dataclass(frozen=True)
class Pose:
    """A rigid camera pose ``T_world_cam`` (camera-to-world, OpenCV axes), float64.

    The matrix is copied and made read-only on construction, so a Pose can be shared across
    threads and stored in events without anyone mutating it.
    """

    T_world_cam: np.ndarray

    def __post_init__(self) -> None:
        try:
            matrix = np.array(self.T_world_cam, dtype=np.float64, copy=True)
        except (TypeError, ValueError) as exc:  # not numbers
            raise InputError(f"T_world_cam must be a 4x4 array of numbers: {exc}") from exc
        if matrix.shape != (4, 4):
            raise InputError(f"T_world_cam must be 4x4, got shape {matrix.shape}")
        matrix.setflags(write=False)
        object.__setattr__(self, "T_world_cam", matrix)

    @classmethod
    def identity(cls) -> Pose:
        return cls(np.eye(4))

    @classmethod
    def from_rt(cls, rotation: np.ndarray, translation: np.ndarray) -> Pose:
        matrix = np.eye(4)
        try:
            matrix[:3, :3] = rotation
            matrix[:3, 3] = np.asarray(translation, dtype=np.float64).reshape(3)
        except (TypeError, ValueError) as exc:
            raise InputError(
                f"a pose needs a 3x3 rotation and 3 translation numbers: {exc}"
            ) from exc
        return cls(matrix)

    @property
    def rotation(self) -> np.ndarray:
        """3x3 rotation of the camera in the world frame (read-only view)."""
        return self.T_world_cam[:3, :3]

    @property
    def translation(self) -> np.ndarray:
        """Camera centre in world coordinates (read-only view)."""
        return self.T_world_cam[:3, 3]

    def as_quat_xyzw(self) -> np.ndarray:
        """Rotation as a unit quaternion, scalar last (ROS, SciPy, TUM files)."""
        return quat_xyzw_from_rotation(self.rotation)

    def as_quat_wxyz(self) -> np.ndarray:
        """Rotation as a unit quaternion, scalar first (Eigen, ARKit's simd_quatf order)."""
        return quat_wxyz_from_rotation(self.rotation)

    def inverse(self) -> Pose:
        """``T_cam_world`` as a Pose."""
        R = self.rotation
        out = np.eye(4)
        out[:3, :3] = R.T
        out[:3, 3] = -R.T @ self.translation
        return Pose(out)

    def is_rigid(self, atol: float = 1e-6) -> bool:
        return check_rigid(self.T_world_cam, atol=atol)


@dataclass(frozen=True)
class MapStatus:
    """A snapshot of the tracker's map."""

    num_keyframes: int
    cache_bytes: int
    generation: int  # increments on every accepted map rebuild (or load)
    rebuilding: bool  # a rebuild is running (asynchronous mapping)
    keyframe_ids: tuple[int, ...] = ()
    # a keyframe candidate waits for the running rebuild (it starts when that one is installed)
    keyframe_waiting: bool = False
    # waiting candidates replaced by newer ones because a rebuild outlasted a keyframe interval
    deferred_replaced: int = 0
    # mapping passes that failed (backend exception or non-finite output) since the tracker began
    failed_passes: int = 0
    # the latest failure (its ``__cause__`` is the backend's exception); None once a pass succeeds
    last_error: MappingFailedError | None = None
    # no mapping pass starts before this frame index (backoff after a failure); None: no backoff
    retry_at_frame: int | None = None
    # frames whose tracking pass failed (see ``FrameResult.error``) since the tracker began
    failed_tracks: int = 0
    # the world frame's units and axes (``kvtracker_sdk.world``): metric? gravity-aligned?
    world: MapWorld = MapWorld()
    # each scale source's latest estimate of the world's unit, with its uncertainty
    scale_estimates: tuple[ScaleEstimate, ...] = ()
    # the up direction measured from gravity readings (None: no reading yet)
    gravity: GravityEstimate | None = None


class RegionSource(str, enum.Enum):
    """Where a frame's object region (``FrameResult.region``) comes from."""

    GIVEN = "given"  # the app passed a mask or a box with this frame
    SEGMENTED = "segmented"  # the app's ``Segmenter`` answered the predicted region's prompt
    PREDICTED = "predicted"  # the map's object points projected with this frame's tracked pose
    HELD = "held"  # no trusted pose (loss, relocalisation, no map yet): the last region, kept


@dataclass(frozen=True)
class ObjectRegion:
    """The object's region in one input image (pixels of the pushed frame).

    ``box``: the object's tight box (x0, y0, x1, y1), x1/y1 exclusive (``geometry/boxes.py``);
    ``context_box``: ``box`` dilated by ``object.crop_margin_px`` (the KV-Tracker paper's 50 px of
    context) and clipped to the image; ``mask``: bool [H, W] of the object's pixels (a box given
    alone gives its rectangle), made on access from a bit-packed crop, so that a long run's
    results stay small; ``source``: see ``RegionSource``; ``frame_index``: the frame the region
    was made for (an older one when ``source`` is HELD); ``image_size``: (H, W).
    Build one from a mask with ``ObjectRegion.from_mask``.
    """

    box: ImageBox
    context_box: ImageBox
    source: RegionSource
    frame_index: int
    image_size: tuple[int, int]
    mask_window: tuple[int, int, int, int]  # (row0, col0, rows, cols) of the packed mask crop
    mask_bits: np.ndarray = field(repr=False)  # np.packbits of the crop, row-major

    def __post_init__(self) -> None:
        self.mask_bits.setflags(write=False)

    @classmethod
    def from_mask(
        cls, mask: np.ndarray, *, box: ImageBox, context_box: ImageBox, source: RegionSource,
        frame_index: int,
    ) -> ObjectRegion:
        """A region over bool [H, W] ``mask`` (stored as its packed crop to the mask's pixels)."""
        mask = np.asarray(mask, dtype=bool)
        rows = np.flatnonzero(mask.any(axis=1))
        cols = np.flatnonzero(mask.any(axis=0))
        if rows.size == 0:
            window = (0, 0, 0, 0)
            bits = np.zeros(0, dtype=np.uint8)
        else:
            window = (int(rows[0]), int(cols[0]), int(rows[-1] - rows[0] + 1),
                      int(cols[-1] - cols[0] + 1))
            crop = mask[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
            bits = np.packbits(crop, axis=None)
        size = (int(mask.shape[0]), int(mask.shape[1]))
        return cls(tuple(float(v) for v in box), tuple(float(v) for v in context_box),  # type: ignore[arg-type]
                   source, int(frame_index), size, window, bits)

    @property
    def mask(self) -> np.ndarray:
        """bool [H, W] of the object's pixels (a new array on every access)."""
        out = np.zeros(self.image_size, dtype=bool)
        row0, col0, rows, cols = self.mask_window
        if rows and cols:
            crop = np.unpackbits(self.mask_bits, count=rows * cols).astype(bool)
            out[row0 : row0 + rows, col0 : col0 + cols] = crop.reshape(rows, cols)
        return out

    def held(self) -> ObjectRegion:
        """This region, kept for a later frame (``source`` HELD; the same mask and boxes)."""
        return replace(self, source=RegionSource.HELD)


@dataclass(frozen=True)
class ObjectFrame:
    """Object mode's anchor for AR content, in the tracker's world frame.

    ``T_world_object``: for an object standing on a support plane (a desk), origin at the centre
    of its extent and z along ``up``, the plane's normal (world, unit; x is keyframe 0's camera x
    laid onto the plane); for a floating object (no plane found, ``up`` None), origin at the
    mean of the map's fused object points and the axes of keyframe 0's camera (OpenCV: x right,
    y down, z forward as keyframe 0 saw the object). ``extent``: an oriented box of the fused
    points, its pose in *object* coordinates (``extent.T_ref_box`` is ``T_object_box``).
    ``num_points``: fused points it was fitted to; ``map_generation``: the map it comes from (it
    moves a little with every rebuild).
    Per frame, ``FrameResult.T_cam_object = inv(T_world_cam) @ T_world_object``.
    """

    T_world_object: np.ndarray
    extent: OrientedBox
    num_points: int
    map_generation: int
    up: np.ndarray | None = None

    def __post_init__(self) -> None:
        matrix = np.array(self.T_world_object, dtype=np.float64, copy=True)
        matrix.setflags(write=False)
        object.__setattr__(self, "T_world_object", matrix)
        if self.up is not None:
            up = np.array(self.up, dtype=np.float64, copy=True)
            up.setflags(write=False)
            object.__setattr__(self, "up", up)


def _frozen_mapping(values: Mapping[str, float] | None) -> Mapping[str, float]:
    return MappingProxyType(dict(values or {}))


@dataclass(frozen=True, kw_only=True)
class FrameResult:
    """What ``Tracker.push_frame`` returns for one frame (built by keyword only).

    ``pose`` is the frame's ``T_world_cam`` in the tracker's world frame; it is None when there is
    no map yet, and flagged by ``pose_valid=False`` while relocalising. ``timings_ms`` holds the
    per-stage wall times (preprocess, track, map, total, ...). ``error`` is set when the backend
    failed to track this frame (then ``pose`` is None and ``pose_valid`` False); the tracker
    carries on with the next frame. ``intrinsics`` is the camera of the *input* image (its pixels, undistorted if the given camera had distortion), and
    ``intrinsics_source`` says whether it was given, predicted by the network (DA3) or
    estimated from the network's local points (Pi3); both None when none is known yet.
    Object mode: ``region`` is the object's region in this frame (``ObjectRegion``; None in scene
    mode) and ``T_cam_object`` the object frame in this camera's frame, 4x4 (None without a
    valid pose or before the map holds object points); ``object_frame`` is the ``ObjectFrame``
    it refers to (``T_cam_object = inv(T_world_cam) @ object_frame.T_world_object``; the object
    frame moves a little with each map rebuild: its ``map_generation`` says which).
    """

    frame_index: int
    timestamp: float | None
    state: TrackingState
    reason: StateReason
    pose: Pose | None
    pose_valid: bool
    confidence: float | None
    keyframe_id: int | None = None
    map_generation: int = 0
    timings_ms: Mapping[str, float] = field(default_factory=dict)
    extras: Mapping[str, Any] = field(default_factory=dict)
    error: TrackingFailedError | None = None
    intrinsics: Camera | None = None
    intrinsics_source: IntrinsicsSource | None = None
    region: ObjectRegion | None = None
    T_cam_object: np.ndarray | None = None
    object_frame: ObjectFrame | None = None

    def __post_init__(self) -> None:
        if self.T_cam_object is not None:
            matrix = np.array(self.T_cam_object, dtype=np.float64, copy=True)
            matrix.setflags(write=False)
            object.__setattr__(self, "T_cam_object", matrix)
        object.__setattr__(self, "timings_ms", _frozen_mapping(self.timings_ms))
        object.__setattr__(self, "extras", MappingProxyType(dict(self.extras)))

    @property
    def is_keyframe(self) -> bool:
        return self.keyframe_id is not None


@dataclass(frozen=True)
class TrackedPose:
    """A valid pose together with the frame it was tracked from (``Tracker.get_tracked_pose``)."""

    pose: Pose
    frame_index: int
    timestamp: float | None


@dataclass(frozen=True)
class TrackerSnapshot:
    """The tracker as of its last finished call, read in one piece (``Tracker.snapshot()``).

    Replaced as a whole (one reference assignment) whenever the tracker changes, so ``state`` and
    ``reason`` always form a pair the state table allows. ``frame_index``/``timestamp`` belong to
    the last processed frame (None before the first); ``pose`` is the last *valid* pose with its own
    frame index and stamp (None before the first and after a map was dropped).
    """

    state: TrackingState
    reason: StateReason
    frame_index: int | None = None
    timestamp: float | None = None
    pose: TrackedPose | None = None
    map_generation: int = 0

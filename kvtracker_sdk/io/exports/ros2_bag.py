"""Record a tracking session as a ROS 2 bag (MCAP storage) with ``rosbags``: no ROS install.

Topics (frames and pose jumps: ``io/exports/ros_frames.py``):

| topic | type | when |
|---|---|---|
| ``/tf_static`` | ``tf2_msgs/TFMessage`` | once: ``base_link -> camera_optical_frame`` (latched QoS) |
| ``/tf`` | ``tf2_msgs/TFMessage`` | each valid pose: ``map -> odom``, ``odom -> base_link`` |
| ``/odom`` | ``nav_msgs/Odometry`` | each valid pose: ``odom -> base_link``, covariance from confidence |
| ``/kvtracker/path`` | ``nav_msgs/Path`` | every ``path_every`` valid poses and at the end: base_link in map |
| ``/camera/camera_info`` | ``sensor_msgs/CameraInfo`` | each frame once intrinsics are known |
| ``/kvtracker/map_points`` | ``sensor_msgs/PointCloud2`` | each map update: the fused cloud in map |
| ``/kvtracker/keyframes`` | ``visualization_msgs/MarkerArray`` | each map update: keyframe frustums |
| ``/diagnostics`` | ``diagnostic_msgs/DiagnosticArray`` | each frame: state, reason, confidence |

Frames without a valid pose (RELOCALIZING, MAPPING) publish no TF and no odometry: their
diagnostics say why (level WARN). Stamps are the frames' timestamps (seconds -> integer ns),
also used as the bag's record times; a map update is stamped with the latest frame's time.

CameraInfo: the intrinsics resized to the pushed frames (the model saw the whole frame resized:
scene mode; an object-mode crop is not reflected).

Odometry covariance: diagonal, position std ``position_sigma / c`` (world units) and rotation std
``rotation_sigma / c`` (radians), c = the frame's confidence clipped to [1e-3, 1] (1 when the
tracker computed none). The bag is written into a temporary folder beside ``path`` and renamed
into place by ``close()``; an existing ``path`` is refused (rosbag2 never overwrites).
"""

from __future__ import annotations

import os
import shutil
import threading
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.errors import ConfigError, MissingDependencyError
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.io.exports.intrinsics import estimate_intrinsics
from kvtracker_sdk.io.exports.map_export import fused_point_cloud
from kvtracker_sdk.io.exports.ros2_messages import RosMessages
from kvtracker_sdk.io.exports.ros_frames import (
    FrameNames,
    OdometrySplit,
    checked_extrinsic,
    map_from_world,
    map_in_world,
)
from kvtracker_sdk.types import FrameResult, TrackingState

__all__ = ["Ros2BagWriter", "TOPICS", "write_ros2_bag"]

TOPICS: dict[str, str] = {
    "/tf_static": "tf2_msgs/msg/TFMessage",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/odom": "nav_msgs/msg/Odometry",
    "/kvtracker/path": "nav_msgs/msg/Path",
    "/camera/camera_info": "sensor_msgs/msg/CameraInfo",
    "/kvtracker/map_points": "sensor_msgs/msg/PointCloud2",
    "/kvtracker/keyframes": "visualization_msgs/msg/MarkerArray",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}
_LEVEL = {TrackingState.TRACKING: 0, TrackingState.INIT: 1, TrackingState.MAPPING: 1,
          TrackingState.RELOCALIZING: 1}  # DiagnosticStatus OK / WARN


def stamp_ns(seconds: float) -> int:
    """Seconds (float) -> integer nanoseconds, rounded (the bag's and the headers' time)."""
    return int(round(float(seconds) * 1e9))


class Ros2BagWriter:
    """Writes one session's frames and map updates into a new rosbag2 folder ``path`` (MCAP).

    Feed it ``write_frame(result, width, height)`` for every pushed frame and
    ``write_map(tracker.keyframe_map)`` on map updates (any thread); ``close()`` finishes it.
    ``intrinsics``: the camera's calibration at the frames' size; None: each frame's
    ``FrameResult.intrinsics`` when the tracker reports one, else estimated from the first map's
    keyframes and resized to the frames. ``T_base_optical``: the static extrinsic.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        intrinsics: Camera | None = None,
        T_base_optical: np.ndarray | None = None,
        frames: FrameNames = FrameNames(),
        position_sigma: float = 0.01,
        rotation_sigma: float = 0.01,
        path_every: int = 10,
        max_points: int = 100_000,
        min_confidence: float = 0.5,
        frustum_size: float = 0.1,
        gravity_aligned: bool = False,
    ) -> None:
        try:
            from rosbags.rosbag2 import StoragePlugin, Writer
        except ImportError as exc:
            raise MissingDependencyError.for_extra(
                "ros", "writing ROS 2 bags needs rosbags") from exc
        self.path = Path(path)
        if self.path.exists():
            raise ConfigError(f"{self.path} exists: a ROS 2 bag is written into a new folder")
        self._messages = RosMessages()
        self.frames = frames
        self.T_base_optical = checked_extrinsic(T_base_optical)
        self.intrinsics = intrinsics
        self._given = intrinsics is not None  # else FrameResult.intrinsics, else fitted to the map
        self.position_sigma, self.rotation_sigma = float(position_sigma), float(rotation_sigma)
        self.path_every, self.max_points = max(1, int(path_every)), int(max_points)
        self.min_confidence, self.frustum_size = float(min_confidence), float(frustum_size)
        # written inside a hidden sibling folder under its final name (rosbag2 names its storage
        # file after the folder), then moved into place
        self._staging = self.path.with_name(f".{self.path.name}.partial")
        shutil.rmtree(self._staging, ignore_errors=True)  # a crashed earlier attempt
        self._staging.mkdir(parents=True)
        self._tmp = self._staging / self.path.name
        self._writer = Writer(self._tmp, version=8, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._connections = {topic: self._connect(topic, msgtype) for topic, msgtype in TOPICS.items()}
        self._lock = threading.Lock()
        self._split = OdometrySplit()
        self._last_ns: int | None = None
        self._previous_valid = False
        self._generation: int | None = None
        self._path: tuple[list[int], list[np.ndarray]] = ([], [])
        self._path_written = 0  # poses in the last published path
        self._static_written = False
        self._closed = False
        # the world is z up (gravity readings were given): map = world; else map follows the
        # camera's body axes. Set from each map written (``write_map``), so a world levelled
        # during a live run switches with its map update (a new generation: a pose jump in odom)
        self.gravity_aligned = bool(gravity_aligned)
        self.counts: dict[str, int] = dict.fromkeys(TOPICS, 0)

    def _connect(self, topic: str, msgtype: str) -> Any:
        qos: tuple[Any, ...] = ()
        if topic == "/tf_static":  # latched, as tf2's static broadcaster: late subscribers get it
            from rosbags.interfaces import (
                Qos,
                QosDurability,
                QosHistory,
                QosLiveliness,
                QosReliability,
                QosTime,
            )
            never = QosTime(sec=0, nsec=0)
            qos = (Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE,
                       QosDurability.TRANSIENT_LOCAL, never, never, QosLiveliness.AUTOMATIC,
                       never, False),)
        return self._writer.add_connection(topic, msgtype, typestore=self._messages.store,
                                           offered_qos_profiles=qos)

    def _write(self, topic: str, time_ns: int, message: Any) -> None:
        data = self._messages.store.serialize_cdr(message, TOPICS[topic])
        self._writer.write(self._connections[topic], time_ns, data)
        self.counts[topic] += 1

    # ------------------------------------------------------------------ frames
    def write_frame(self, result: FrameResult, width: int, height: int) -> None:
        """One pushed frame (``width`` x ``height`` pixels) and its result."""
        if result.timestamp is None:
            raise ConfigError("ROS bags need frame timestamps: push frames with timestamp=...")
        now = stamp_ns(result.timestamp)
        names = self.frames
        with self._lock:
            self._last_ns = now
            if not self._static_written:
                self._write("/tf_static", now, self._messages.tf([self._messages.transform(
                    now, names.base, names.camera, self.T_base_optical)]))
                self._static_written = True
            valid = result.pose_valid and result.pose is not None
            if valid and result.pose is not None:
                continuous = self._previous_valid and result.map_generation == self._generation
                T_map_base = map_from_world(result.pose.T_world_cam, self.T_base_optical,
                                            gravity_aligned=self.gravity_aligned)
                T_map_odom, T_odom_base = self._split.update(T_map_base, continuous=continuous)
                self._write("/tf", now, self._messages.tf([
                    self._messages.transform(now, names.map, names.odom, T_map_odom),
                    self._messages.transform(now, names.odom, names.base, T_odom_base)]))
                self._write("/odom", now, self._messages.odometry(
                    now, names.odom, names.base, T_odom_base, self._covariance(result.confidence)))
                self._path[0].append(now)
                self._path[1].append(T_map_base)
                if len(self._path[0]) - self._path_written >= self.path_every:
                    self._write_path(now)
                self._generation = result.map_generation
            self._previous_valid = valid
            camera = self.intrinsics
            if not self._given and result.intrinsics is not None:  # the tracker's own camera
                camera = Camera.of(result.intrinsics)
            if camera is not None:
                if (camera.width, camera.height) != (width, height):
                    camera = camera.resized(width, height)
                self._write("/camera/camera_info", now,
                            self._messages.camera_info(now, names.camera, camera))
            self._write("/diagnostics", now, self._diagnostics(now, result))

    def _covariance(self, confidence: float | None) -> np.ndarray:
        c = 1.0 if confidence is None else float(np.clip(confidence, 1e-3, 1.0))
        variances = [(self.position_sigma / c) ** 2] * 3 + [(self.rotation_sigma / c) ** 2] * 3
        return np.diag(variances)

    def _diagnostics(self, now: int, result: FrameResult) -> Any:
        values = {
            "state": result.state.value, "reason": result.reason.value,
            "frame_index": str(result.frame_index), "pose_valid": str(bool(result.pose_valid)),
            "confidence": "" if result.confidence is None else f"{result.confidence:.6f}",
            "map_generation": str(result.map_generation),
            "pose_jumps": str(self._split.jumps),
        }
        message = f"{result.state.value} ({result.reason.value})"
        return self._messages.diagnostics(now, _LEVEL[result.state], message, values)

    def _write_path(self, now: int) -> None:
        stamps, poses = self._path
        self._path_written = len(stamps)
        self._write("/kvtracker/path", now,
                    self._messages.path(now, self.frames.map, stamps, poses))

    # ------------------------------------------------------------------ map
    def estimate_intrinsics(self, keyframe_map: KeyframeMap) -> None:
        """Without a calibration: fit the intrinsics to the map's keyframes (once)."""
        if self.intrinsics is None and keyframe_map.keyframes:
            self.intrinsics = estimate_intrinsics(
                np.stack([kf.local_points for kf in keyframe_map.keyframes]),
                np.stack([kf.confidence_map for kf in keyframe_map.keyframes]),
                min_confidence=self.min_confidence)

    def write_map(self, keyframe_map: KeyframeMap | None) -> None:
        """The map's fused cloud and keyframe frustums (map frame), at the latest frame's time."""
        if keyframe_map is None or not keyframe_map.keyframes:
            return
        points, colors, _ = fused_point_cloud(keyframe_map, min_confidence=self.min_confidence)
        if len(points) > self.max_points:
            keep = np.random.default_rng(0).choice(len(points), self.max_points, replace=False)
            points, colors = points[np.sort(keep)], colors[np.sort(keep)]
        with self._lock:
            self.gravity_aligned = keyframe_map.world.gravity_aligned
        T_map_world = map_in_world(self.T_base_optical, gravity_aligned=self.gravity_aligned)
        points_map = points @ T_map_world[:3, :3].T + T_map_world[:3, 3]
        poses = {kf.keyframe_id: T_map_world @ kf.T_world_cam for kf in keyframe_map.keyframes}
        with self._lock:
            self.estimate_intrinsics(keyframe_map)
            assert self.intrinsics is not None
            now = self._last_ns if self._last_ns is not None else 0
            model_camera = self.intrinsics.resized(*keyframe_map.resolution[::-1])
            self._write("/kvtracker/map_points", now, self._messages.point_cloud(
                now, self.frames.map, points_map, colors))
            self._write("/kvtracker/keyframes", now, self._messages.keyframe_markers(
                now, self.frames.map, poses, self.frustum_size, model_camera))

    # ------------------------------------------------------------------ closing
    def close(self, *, keep: bool = True) -> Path | None:
        """Finish the bag and move it into place (``keep=False`` discards it). Idempotent."""
        with self._lock:
            if self._closed:
                return self.path if keep else None
            self._closed = True
            if keep and len(self._path[0]) > self._path_written:
                self._write_path(self._path[0][-1])  # the complete path as the last message
            self._writer.close()
        if keep:
            os.replace(self._tmp, self.path)
        shutil.rmtree(self._staging, ignore_errors=True)
        return self.path if keep else None

    def __enter__(self) -> Ros2BagWriter:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.close(keep=error is None)


def write_ros2_bag(
    path: str | os.PathLike[str],
    results: list[FrameResult],
    keyframe_map: KeyframeMap | None,
    *,
    image_size: tuple[int, int],
    **options: Any,
) -> dict[str, int]:
    """Write a finished run (its frame results and final map) as a ROS 2 bag at ``path``.

    ``image_size`` (width, height) of the frames; ``options`` as :class:`Ros2BagWriter`
    (``intrinsics``, ``T_base_optical``, ...). Returns the message count per topic.
    """
    width, height = image_size
    if keyframe_map is not None:  # the run's final world: z up if it was levelled
        options.setdefault("gravity_aligned", keyframe_map.world.gravity_aligned)
    with Ros2BagWriter(path, **options) as writer:
        if keyframe_map is not None:
            writer.estimate_intrinsics(keyframe_map)  # camera_info from the first frame on
        for result in results:
            writer.write_frame(result, width, height)
        writer.write_map(keyframe_map)
    return writer.counts

"""``TrackerNode``: a thin ROS 2 node around a :class:`Tracker` (needs a ROS 2 install: rclpy).

In:  ``image`` (``sensor_msgs/Image``, rgb8 / bgr8 / mono8) and ``camera_info``
     (``sensor_msgs/CameraInfo``; kept for apps and for the intrinsics seam, not needed to track).
Out: ``/tf`` (``map -> odom -> base_link``), ``/tf_static`` (``base_link ->
     camera_optical_frame``), ``odom`` (``nav_msgs/Odometry``) and ``/diagnostics`` (state and
     reason) — the frames and the pose-jump rule of ``io/exports/ros_frames.py``, as in the bags.
Services (``std_srvs/Trigger``): ``~/save_map`` and ``~/load_map`` (the ``map_path``
     parameter), ``~/reset``.

rclpy and the message packages are imported when a node is made (an ``ImportError`` becomes a
``MissingDependencyError``), so importing this module needs no ROS. Frames are tracked in the
subscription callback, on the executor's thread; a frame the tracker refuses is logged and
dropped, never raised into the executor.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from kvtracker_sdk.errors import InputError, KVTrackerError, MissingDependencyError
from kvtracker_sdk.geometry.se3 import quat_xyzw_from_rotation
from kvtracker_sdk.io.exports.ros_frames import (
    FrameNames,
    OdometrySplit,
    checked_extrinsic,
    map_from_world,
)
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.types import FrameResult, TrackingState

if TYPE_CHECKING:
    from kvtracker_sdk.tracking.facade.tracker import Tracker

__all__ = ["TrackerNode", "image_from_message"]

_log = get_logger(__name__)
_CHANNELS = {"rgb8": 3, "bgr8": 3, "mono8": 1}


_ROS_NAMES = {  # name -> module that defines it
    "Node": "rclpy.node", "QoSProfile": "rclpy.qos", "DurabilityPolicy": "rclpy.qos",
    "Image": "sensor_msgs.msg", "CameraInfo": "sensor_msgs.msg", "Odometry": "nav_msgs.msg",
    "TransformStamped": "geometry_msgs.msg", "TFMessage": "tf2_msgs.msg",
    "DiagnosticArray": "diagnostic_msgs.msg", "DiagnosticStatus": "diagnostic_msgs.msg",
    "KeyValue": "diagnostic_msgs.msg", "Trigger": "std_srvs.srv",
}


def _ros() -> dict[str, Any]:
    """The rclpy classes and message types the node uses, by name."""
    try:
        return {name: getattr(importlib.import_module(module), name)
                for name, module in _ROS_NAMES.items()}
    except ImportError as exc:
        raise MissingDependencyError(
            "the ROS 2 node needs a ROS 2 installation (rclpy and the common message packages): "
            "source /opt/ros/$ROS_DISTRO/setup.bash") from exc


def image_from_message(message: Any) -> np.ndarray:
    """``sensor_msgs/Image`` (rgb8, bgr8, mono8; rows may be padded) -> [H, W, 3] uint8 RGB."""
    channels = _CHANNELS.get(message.encoding)
    if channels is None:
        raise InputError(f"image encoding {message.encoding!r}: expected rgb8, bgr8 or mono8")
    height, width, step = int(message.height), int(message.width), int(message.step)
    data = np.frombuffer(bytes(message.data), dtype=np.uint8)
    if step < width * channels or data.size < step * height:
        raise InputError(f"image of {data.size} bytes does not hold {height} rows of {step}")
    rows = data[: step * height].reshape(height, step)[:, : width * channels]
    image = rows.reshape(height, width, channels)
    if message.encoding == "bgr8":
        image = image[..., ::-1]
    elif channels == 1:
        image = np.repeat(image, 3, axis=2)
    return np.ascontiguousarray(image)


class TrackerNode:
    """Wraps ``tracker`` in an rclpy node named ``name`` (see the module docstring)."""

    def __init__(
        self,
        tracker: Tracker,
        *,
        name: str = "kvtracker",
        map_path: str = "kvtracker.kvmap",
        T_base_optical: np.ndarray | None = None,
        frames: FrameNames = FrameNames(),
    ) -> None:
        self._m = _ros()
        self.tracker = tracker
        self.frames = frames
        self.T_base_optical = checked_extrinsic(T_base_optical)
        self.node = self._m["Node"](name)
        self.node.declare_parameter("map_path", map_path)
        self.camera_info: Any = None  # the latest CameraInfo message
        self._split = OdometrySplit()
        self._previous_valid = False
        self._generation: int | None = None
        latched = self._m["QoSProfile"](
            depth=1, durability=self._m["DurabilityPolicy"].TRANSIENT_LOCAL)
        self._tf = self.node.create_publisher(self._m["TFMessage"], "/tf", 10)
        self._tf_static = self.node.create_publisher(self._m["TFMessage"], "/tf_static", latched)
        self._odom = self.node.create_publisher(self._m["Odometry"], "odom", 10)
        self._diagnostics = self.node.create_publisher(self._m["DiagnosticArray"], "/diagnostics", 10)
        self.node.create_subscription(self._m["Image"], "image", self.on_image, 1)
        self.node.create_subscription(self._m["CameraInfo"], "camera_info", self.on_camera_info, 1)
        trigger = self._m["Trigger"]
        self.node.create_service(trigger, "~/save_map", self._save)
        self.node.create_service(trigger, "~/load_map", self._load)
        self.node.create_service(trigger, "~/reset", self._reset)
        self._static_sent = False

    # ------------------------------------------------------------------ inputs
    def on_camera_info(self, message: Any) -> None:
        self.camera_info = message

    def on_image(self, message: Any) -> FrameResult | None:
        """Track one image; publish its TF, odometry and diagnostics. None if it was refused."""
        stamp = message.header.stamp
        seconds = int(stamp.sec) + int(stamp.nanosec) * 1e-9
        try:
            result = self.tracker.push_frame(image_from_message(message), timestamp=seconds)
        except KVTrackerError as exc:  # bad input: the tracker is untouched, the node goes on
            _log.warning("frame refused", reason=str(exc))
            return None
        self._publish(result, stamp)
        return result

    # ------------------------------------------------------------------ outputs
    def _publish(self, result: FrameResult, stamp: Any) -> None:
        names = self.frames
        if not self._static_sent:
            self._tf_static.publish(self._tf_message(
                [self._transform(stamp, names.base, names.camera, self.T_base_optical)]))
            self._static_sent = True
        valid = result.pose_valid and result.pose is not None
        if valid and result.pose is not None:
            continuous = self._previous_valid and result.map_generation == self._generation
            kf_map = self.tracker.keyframe_map  # a levelled world is the map frame (z up)
            aligned = kf_map is not None and kf_map.world.gravity_aligned
            T_map_base = map_from_world(result.pose.T_world_cam, self.T_base_optical,
                                        gravity_aligned=aligned)
            T_map_odom, T_odom_base = self._split.update(T_map_base, continuous=continuous)
            self._tf.publish(self._tf_message([
                self._transform(stamp, names.map, names.odom, T_map_odom),
                self._transform(stamp, names.odom, names.base, T_odom_base)]))
            odometry = self._m["Odometry"]()
            odometry.header.stamp, odometry.header.frame_id = stamp, names.odom
            odometry.child_frame_id = names.base
            _fill_pose(odometry.pose.pose, T_odom_base)
            self._odom.publish(odometry)
            self._generation = result.map_generation
        self._previous_valid = valid
        self._diagnostics.publish(self._diagnostic(result, stamp))

    def _transform(self, stamp: Any, parent: str, child: str, T: np.ndarray) -> Any:
        message = self._m["TransformStamped"]()
        message.header.stamp, message.header.frame_id = stamp, parent
        message.child_frame_id = child
        t, q = message.transform.translation, message.transform.rotation
        t.x, t.y, t.z = (float(v) for v in T[:3, 3])
        q.x, q.y, q.z, q.w = (float(v) for v in quat_xyzw_from_rotation(T[:3, :3]))
        return message

    def _tf_message(self, transforms: list[Any]) -> Any:
        message = self._m["TFMessage"]()
        message.transforms = transforms
        return message

    def _diagnostic(self, result: FrameResult, stamp: Any) -> Any:
        status = self._m["DiagnosticStatus"]()
        status.level = bytes([0 if result.state is TrackingState.TRACKING else 1])
        status.name, status.hardware_id = "kvtracker: tracker", "kvtracker"
        status.message = f"{result.state.value} ({result.reason.value})"
        status.values = [self._key_value(k, v) for k, v in (
            ("state", result.state.value), ("reason", result.reason.value),
            ("frame_index", str(result.frame_index)), ("pose_valid", str(result.pose_valid)),
            ("map_generation", str(result.map_generation)))]
        array = self._m["DiagnosticArray"]()
        array.header.stamp = stamp
        array.status = [status]
        return array

    def _key_value(self, key: str, value: str) -> Any:
        pair = self._m["KeyValue"]()
        pair.key, pair.value = key, value
        return pair

    # ------------------------------------------------------------------ services
    def _map_path(self) -> Path:
        return Path(str(self.node.get_parameter("map_path").value))

    def _save(self, _request: Any, response: Any) -> Any:
        def save() -> str:
            info = self.tracker.save_map(self._map_path())
            return f"saved {self._map_path()} ({info.num_keyframes} keyframes)"
        return self._service(response, save)

    def _load(self, _request: Any, response: Any) -> Any:
        def load() -> str:
            self.tracker.initialize(map=self._map_path())
            self._previous_valid = False  # the next pose starts a new odometry segment
            return f"loaded {self._map_path()}: relocalising"
        return self._service(response, load)

    def _reset(self, _request: Any, response: Any) -> Any:
        def reset() -> str:
            self.tracker.reset()
            self._previous_valid = False
            return "reset"
        return self._service(response, reset)

    @staticmethod
    def _service(response: Any, action: Any) -> Any:
        try:
            response.message, response.success = str(action()), True
        except KVTrackerError as exc:  # reported to the caller, never raised into the executor
            response.message, response.success = str(exc), False
        return response


def _fill_pose(pose: Any, T: np.ndarray) -> None:
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in T[:3, 3])
    q = quat_xyzw_from_rotation(T[:3, :3])
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (
        float(v) for v in q)

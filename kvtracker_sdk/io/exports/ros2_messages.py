"""ROS 2 messages built with ``rosbags``' typestore (no ROS install), from SDK values.

Each builder takes numpy values in the frames named by its caller and returns a message object of
the ``ros2_humble`` typestore; the writer serialises them (CDR). Quaternions go through the
named ``quat_xyzw`` function (ROS order: x, y, z, w).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from kvtracker_sdk.errors import MissingDependencyError
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.geometry.se3 import quat_xyzw_from_rotation

__all__ = ["RosMessages"]

_FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32


def typestore() -> Any:
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:
        raise MissingDependencyError.for_extra("ros", "writing ROS 2 bags needs rosbags") from exc
    return get_typestore(Stores.ROS2_HUMBLE)


class RosMessages:
    """Message builders over one typestore (``types`` maps 'pkg/msg/Name' to its class)."""

    def __init__(self) -> None:
        self.store = typestore()
        self.types = self.store.types

    def _t(self, name: str) -> Any:
        return self.types[name]

    # ------------------------------------------------------------------ basics
    def header(self, stamp_ns: int, frame_id: str) -> Any:
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        time = self._t("builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec)
        return self._t("std_msgs/msg/Header")(stamp=time, frame_id=frame_id)

    def pose(self, T: np.ndarray) -> Any:
        x, y, z = (float(v) for v in T[:3, 3])
        qx, qy, qz, qw = (float(v) for v in quat_xyzw_from_rotation(T[:3, :3]))
        return self._t("geometry_msgs/msg/Pose")(
            position=self._t("geometry_msgs/msg/Point")(x=x, y=y, z=z),
            orientation=self._t("geometry_msgs/msg/Quaternion")(x=qx, y=qy, z=qz, w=qw),
        )

    def transform(self, stamp_ns: int, parent: str, child: str, T: np.ndarray) -> Any:
        pose = self.pose(T)
        p = pose.position
        return self._t("geometry_msgs/msg/TransformStamped")(
            header=self.header(stamp_ns, parent),
            child_frame_id=child,
            transform=self._t("geometry_msgs/msg/Transform")(
                translation=self._t("geometry_msgs/msg/Vector3")(x=p.x, y=p.y, z=p.z),
                rotation=pose.orientation,
            ),
        )

    def tf(self, transforms: list[Any]) -> Any:
        return self._t("tf2_msgs/msg/TFMessage")(transforms=transforms)

    # ------------------------------------------------------------------ motion
    def odometry(
        self, stamp_ns: int, parent: str, child: str, T: np.ndarray, covariance: np.ndarray
    ) -> Any:
        zero = self._t("geometry_msgs/msg/Vector3")(x=0.0, y=0.0, z=0.0)
        return self._t("nav_msgs/msg/Odometry")(
            header=self.header(stamp_ns, parent),
            child_frame_id=child,
            pose=self._t("geometry_msgs/msg/PoseWithCovariance")(
                pose=self.pose(T), covariance=np.asarray(covariance, np.float64).reshape(36)
            ),
            twist=self._t("geometry_msgs/msg/TwistWithCovariance")(
                twist=self._t("geometry_msgs/msg/Twist")(linear=zero, angular=zero),
                covariance=np.zeros(36),
            ),
        )

    def path(self, stamp_ns: int, frame: str, stamps_ns: list[int], poses: list[np.ndarray]) -> Any:
        stamped = self._t("geometry_msgs/msg/PoseStamped")
        return self._t("nav_msgs/msg/Path")(
            header=self.header(stamp_ns, frame),
            poses=[stamped(header=self.header(s, frame), pose=self.pose(T))
                   for s, T in zip(stamps_ns, poses, strict=True)],
        )

    # ------------------------------------------------------------------ camera and map
    def camera_info(self, stamp_ns: int, frame: str, camera: Camera) -> Any:
        """ROS's pixel convention is OpenCV's (and the SDK's): K is written as it is."""
        K = camera.K()
        P = np.zeros((3, 4))
        P[:, :3] = K
        return self._t("sensor_msgs/msg/CameraInfo")(
            header=self.header(stamp_ns, frame), height=camera.height, width=camera.width,
            distortion_model="plumb_bob", d=np.zeros(5), k=K.reshape(9),
            r=np.eye(3).reshape(9), p=P.reshape(12), binning_x=0, binning_y=0,
            roi=self._t("sensor_msgs/msg/RegionOfInterest")(
                x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
        )

    def point_cloud(self, stamp_ns: int, frame: str, points: np.ndarray, colors: np.ndarray) -> Any:
        """x, y, z float32 and PCL's packed ``rgb`` (0x00RRGGBB read as a float32), 16 bytes a
        point, little-endian; Foxglove and RViz colour by ``rgb``."""
        count = len(points)
        record = np.zeros(count, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
        for k, axis in enumerate("xyz"):
            record[axis] = points[:, k]
        rgb = np.asarray(colors, dtype=np.uint32)
        record["rgb"] = (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
        field = self._t("sensor_msgs/msg/PointField")
        fields = [field(name=n, offset=4 * k, datatype=_FLOAT32, count=1)
                  for k, n in enumerate(("x", "y", "z", "rgb"))]
        return self._t("sensor_msgs/msg/PointCloud2")(
            header=self.header(stamp_ns, frame), height=1, width=count, fields=fields,
            is_bigendian=False, point_step=16, row_step=16 * count,
            data=np.frombuffer(record.tobytes(), dtype=np.uint8), is_dense=True,
        )

    def keyframe_markers(
        self, stamp_ns: int, frame: str, poses: dict[int, np.ndarray], size: float,
        camera: Camera | None,
    ) -> Any:
        """A DELETEALL, then one LINE_LIST frustum per keyframe (``ns`` "keyframes", id = the
        keyframe id), posed by ``T_frame_cam`` (camera at the apex, OpenCV axes)."""
        marker = self._t("visualization_msgs/msg/Marker")
        markers = [self._marker(marker, stamp_ns, frame, 0, marker.DELETEALL, np.eye(4), [], size)]
        corners = _frustum_lines(camera, size)
        for keyframe_id, T in sorted(poses.items()):
            markers.append(self._marker(marker, stamp_ns, frame, keyframe_id, marker.ADD, T,
                                        corners, size))
        return self._t("visualization_msgs/msg/MarkerArray")(markers=markers)

    def _marker(
        self, marker: Any, stamp_ns: int, frame: str, marker_id: int, action: int, T: np.ndarray,
        lines: list[np.ndarray], size: float,
    ) -> Any:
        point = self._t("geometry_msgs/msg/Point")
        return marker(
            header=self.header(stamp_ns, frame), ns="keyframes", id=int(marker_id),
            type=marker.LINE_LIST, action=action, pose=self.pose(T),
            scale=self._t("geometry_msgs/msg/Vector3")(x=size * 0.02, y=0.0, z=0.0),
            color=self._t("std_msgs/msg/ColorRGBA")(r=0.1, g=0.6, b=1.0, a=1.0),
            lifetime=self._t("builtin_interfaces/msg/Duration")(sec=0, nanosec=0),
            frame_locked=False,
            points=[point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in lines],
            colors=[], texture_resource="",
            texture=self._t("sensor_msgs/msg/CompressedImage")(
                header=self.header(stamp_ns, frame), format="", data=np.zeros(0, np.uint8)),
            uv_coordinates=[], text="", mesh_resource="",
            mesh_file=self._t("visualization_msgs/msg/MeshFile")(
                filename="", data=np.zeros(0, np.uint8)),
            mesh_use_embedded_materials=False,
        )

    # ------------------------------------------------------------------ state
    def diagnostics(self, stamp_ns: int, level: int, message: str, values: dict[str, str]) -> Any:
        key_value = self._t("diagnostic_msgs/msg/KeyValue")
        status = self._t("diagnostic_msgs/msg/DiagnosticStatus")(
            level=int(level), name="kvtracker: tracker", message=message, hardware_id="kvtracker",
            values=[key_value(key=k, value=v) for k, v in values.items()],
        )
        return self._t("diagnostic_msgs/msg/DiagnosticArray")(
            header=self.header(stamp_ns, ""), status=[status])


def _frustum_lines(camera: Camera | None, size: float) -> list[np.ndarray]:
    """Pairs of points (LINE_LIST) drawing a frustum of depth ``size`` in the camera frame."""
    if camera is None:
        half_w, half_h = 0.5, 0.375
    else:
        half_w, half_h = camera.width / (2 * camera.fx), camera.height / (2 * camera.fy)
    corners = [np.array([sx * half_w * size, sy * half_h * size, size])
               for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    apex = np.zeros(3)
    lines: list[np.ndarray] = []
    for k, corner in enumerate(corners):
        lines += [apex, corner, corner, corners[(k + 1) % 4]]
    return lines

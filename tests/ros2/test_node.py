"""``TrackerNode`` against a fake rclpy: images in, TF / odometry / diagnostics out with the
bags' frame rules, save / load / reset services, and a clear error without ROS."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.errors import InputError, MissingDependencyError
from kvtracker_sdk.geometry.se3 import rotation_from_quat_xyzw
from kvtracker_sdk.io.exports.ros_frames import DEFAULT_T_BASE_OPTICAL
from kvtracker_sdk.ros2 import TrackerNode, image_from_message
from kvtracker_sdk.types import TrackingState
from tests.ros2.fake_rclpy import Message, Trigger, fake_ros
from tests.tracking.sim_session import SIZE, make_tracker


def image_message(image: np.ndarray, seconds: float, encoding: str = "bgr8", pad: int = 4) -> Any:
    """A sensor_msgs/Image of ``image`` (RGB) with ``pad`` bytes of padding at each row's end."""
    message = Message()
    pixels = image[..., ::-1] if encoding == "bgr8" else image
    rows = pixels.reshape(image.shape[0], -1)
    padded = np.concatenate([rows, np.zeros((rows.shape[0], pad), np.uint8)], axis=1)
    message.height, message.width, message.encoding = image.shape[0], image.shape[1], encoding
    message.step, message.data = padded.shape[1], padded.tobytes()
    message.header.stamp.sec, message.header.stamp.nanosec = int(seconds), round(seconds % 1 * 1e9)
    return message


def _matrix(transform: Any) -> np.ndarray:
    t, q = transform.translation, transform.rotation
    T = np.eye(4)
    T[:3, :3] = rotation_from_quat_xyzw(np.array([q.x, q.y, q.z, q.w]))
    T[:3, 3] = [t.x, t.y, t.z]
    return T


def _call(node: TrackerNode, service: str) -> Any:
    _kind, callback = node.node.services[service]
    return callback(Trigger.Request(), Trigger.Response())


def test_node_tracks_images_publishes_tf_and_serves_maps(tmp_path: Path) -> None:
    backend = SimulatedBackend(orbit(num_frames=60, turns=0.25), seed=1)
    with fake_ros(), make_tracker(backend, keyframing={"interval_frames": 20}) as tracker:
        node = TrackerNode(tracker, map_path=str(tmp_path / "room.kvmap"))
        results = [node.node.subscriptions["image"](image_message(f.image, 100.0 + f.timestamp))
                   for f in backend.frames(SIZE, stop=45, textured=False)]
        publishers = node.node.publishers
        assert publishers["/tf_static"].qos.durability == "transient_local"
        static = publishers["/tf_static"].sent[0].transforms[0]
        np.testing.assert_allclose(_matrix(static.transform), DEFAULT_T_BASE_OPTICAL, atol=1e-12)
        valid = [r for r in results if r is not None and r.pose_valid]
        assert len(valid) == len(publishers["/tf"].sent) == len(publishers["odom"].sent) > 40
        for result, message in zip(valid, publishers["/tf"].sent, strict=True):
            map_odom, odom_base = message.transforms
            assert (map_odom.child_frame_id, odom_base.child_frame_id) == ("odom", "base_link")
            T_map_camera = _matrix(map_odom.transform) @ _matrix(odom_base.transform) @ \
                DEFAULT_T_BASE_OPTICAL
            expected = DEFAULT_T_BASE_OPTICAL @ result.pose.T_world_cam  # type: ignore[union-attr]
            np.testing.assert_allclose(T_map_camera, expected, atol=1e-9)
        status = publishers["/diagnostics"].sent[-1].status[0]
        assert status.message == "TRACKING (BOOTSTRAP)" and status.level == b"\x00"

        saved = _call(node, "~/save_map")
        assert saved.success and (tmp_path / "room.kvmap").is_file(), saved.message
        assert _call(node, "~/reset").success and tracker.state is TrackingState.INIT
        failed = _call(node, "~/save_map")  # no map to save: reported, not raised
        assert not failed.success and failed.message
        assert _call(node, "~/load_map").success
        assert tracker.state is TrackingState.RELOCALIZING

        bad = image_message(np.zeros((4, 4, 3), np.uint8), 200.0, encoding="rgb16")
        assert node.node.subscriptions["image"](bad) is None  # refused, logged, not raised


def test_image_conversion() -> None:
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    for encoding in ("rgb8", "bgr8"):
        np.testing.assert_array_equal(image_from_message(image_message(image, 0.0, encoding)), image)
    gray = image[..., :1]
    converted = image_from_message(image_message(gray, 0.0, "mono8"))
    np.testing.assert_array_equal(converted, np.repeat(gray, 3, axis=2))
    with pytest.raises(InputError, match="encoding"):
        image_from_message(image_message(image, 0.0, "32FC1"))


def test_without_ros_the_node_says_what_is_missing(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "rclpy", None)
    monkeypatch.setitem(sys.modules, "rclpy.node", None)
    with pytest.raises(MissingDependencyError, match="ROS 2 installation"):
        TrackerNode(object())  # type: ignore[arg-type]

"""ROS 2 integration that needs a ROS install (rclpy): :class:`TrackerNode`. Bags are written
without ROS by ``kvtracker_sdk.io.exports.ros2_bag``."""

from kvtracker_sdk.ros2.node import TrackerNode, image_from_message

__all__ = ["TrackerNode", "image_from_message"]

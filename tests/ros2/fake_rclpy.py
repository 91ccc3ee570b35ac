"""A stand-in for rclpy and the ROS message packages the node imports: enough surface to
construct ``TrackerNode``, deliver messages to its callbacks, call its services, and read what
it published. Messages are attribute bags whose nested fields appear when first touched."""

from __future__ import annotations

import sys
import types
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


class Message:
    """A message: nested fields are created on first access (as rclpy's defaults would be)."""

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        value = Message()
        setattr(self, name, value)
        return value


class Publisher:
    def __init__(self, kind: type, topic: str, qos: Any) -> None:
        self.kind, self.topic, self.qos, self.sent = kind, topic, qos, []

    def publish(self, message: Any) -> None:
        assert isinstance(message, self.kind), (type(message), self.kind)
        self.sent.append(message)


class Parameter:
    def __init__(self, value: Any) -> None:
        self.value = value


class Node:
    def __init__(self, name: str) -> None:
        self.name = name
        self.publishers: dict[str, Publisher] = {}
        self.subscriptions: dict[str, Any] = {}
        self.services: dict[str, Any] = {}
        self.parameters: dict[str, Parameter] = {}

    def declare_parameter(self, name: str, value: Any) -> Parameter:
        self.parameters[name] = Parameter(value)
        return self.parameters[name]

    def get_parameter(self, name: str) -> Parameter:
        return self.parameters[name]

    def create_publisher(self, kind: type, topic: str, qos: Any) -> Publisher:
        self.publishers[topic] = Publisher(kind, topic, qos)
        return self.publishers[topic]

    def create_subscription(self, kind: type, topic: str, callback: Any, qos: Any) -> None:
        self.subscriptions[topic] = callback

    def create_service(self, kind: type, name: str, callback: Any) -> None:
        self.services[name] = (kind, callback)


class QoSProfile:
    def __init__(self, *, depth: int, durability: Any = None) -> None:
        self.depth, self.durability = depth, durability


class DurabilityPolicy:
    TRANSIENT_LOCAL = "transient_local"


class Trigger:
    class Request(Message):
        pass

    class Response(Message):
        pass


def _kinds(*names: str) -> dict[str, type]:
    return {name: type(name, (Message,), {}) for name in names}


MODULES: dict[str, dict[str, Any]] = {
    "rclpy": {},
    "rclpy.node": {"Node": Node},
    "rclpy.qos": {"QoSProfile": QoSProfile, "DurabilityPolicy": DurabilityPolicy},
    "sensor_msgs": {}, "sensor_msgs.msg": _kinds("Image", "CameraInfo"),
    "nav_msgs": {}, "nav_msgs.msg": _kinds("Odometry"),
    "geometry_msgs": {}, "geometry_msgs.msg": _kinds("TransformStamped"),
    "tf2_msgs": {}, "tf2_msgs.msg": _kinds("TFMessage"),
    "diagnostic_msgs": {},
    "diagnostic_msgs.msg": _kinds("DiagnosticArray", "DiagnosticStatus", "KeyValue"),
    "std_srvs": {}, "std_srvs.srv": {"Trigger": Trigger},
}


@contextmanager
def fake_ros() -> Iterator[dict[str, types.ModuleType]]:
    """Install the fake modules in ``sys.modules`` for the block (and remove them after)."""
    saved = {name: sys.modules.get(name) for name in MODULES}
    modules = {}
    for name, members in MODULES.items():
        module = types.ModuleType(name)
        module.__dict__.update(members)
        modules[name] = sys.modules[name] = module
    try:
        yield modules
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module

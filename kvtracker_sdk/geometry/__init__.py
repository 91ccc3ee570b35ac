"""Rigid and similarity transforms, alignment and view angles (numpy/scipy only)."""

from kvtracker_sdk.geometry.se3 import (
    check_rigid,
    invert_rigid,
    project_to_rotation,
    quat_wxyz_from_rotation,
    quat_xyzw_from_rotation,
    rotation_angle_deg,
    rotation_from_quat_wxyz,
    rotation_from_quat_xyzw,
)
from kvtracker_sdk.geometry.sim3 import Sim3, umeyama_alignment

__all__ = [
    "Sim3",
    "check_rigid",
    "invert_rigid",
    "project_to_rotation",
    "quat_wxyz_from_rotation",
    "quat_xyzw_from_rotation",
    "rotation_angle_deg",
    "rotation_from_quat_wxyz",
    "rotation_from_quat_xyzw",
    "umeyama_alignment",
]

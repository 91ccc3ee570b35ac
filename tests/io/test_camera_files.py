"""Camera files (SDK JSON, ROS CameraInfo, camera_calibration YAML) and dataset intrinsics."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from kvtracker_sdk.errors import InputError, SourceError
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.io.sources.camera_files import DATASET_CAMERAS, read_camera_file
from kvtracker_sdk.io.sources.sources import SevenScenesSource, open_source
from tests.helpers import dev_dependency, shared_path

EXPECTED = Camera(520.9086, 521.0073, 325.1414, 249.7018, 640, 480,
                  (0.231222, -0.784899, -0.003257, -0.000105, 0.917205))
K = [520.9086, 0.0, 325.1414, 0.0, 521.0073, 249.7018, 0.0, 0.0, 1.0]
D = list(EXPECTED.distortion)

CALIBRATION_YAML = f"""\
image_width: 640
image_height: 480
camera_name: xtion
camera_matrix:
  rows: 3
  cols: 3
  data: {K}
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: {D}
projection_matrix:
  rows: 3
  cols: 4
  data: [520.0, 0.0, 325.0, 0.0, 0.0, 521.0, 249.0, 0.0, 0.0, 0.0, 1.0, 0.0]
"""


def test_sdk_json_and_ros_camera_info(tmp_path: Path) -> None:
    own = tmp_path / "camera.json"
    own.write_text(json.dumps(EXPECTED.to_dict()))
    assert read_camera_file(own) == EXPECTED
    ros = tmp_path / "camera_info.json"  # sensor_msgs/CameraInfo; P is ignored (rectified image)
    ros.write_text(json.dumps({"width": 640, "height": 480, "distortion_model": "plumb_bob",
                               "D": D, "K": K, "P": [1.0] * 12, "R": [1, 0, 0, 0, 1, 0, 0, 0, 1]}))
    assert read_camera_file(ros) == EXPECTED
    ros2 = tmp_path / "ros2.json"  # ROS 2 spells the fields in lower case
    ros2.write_text(json.dumps({"width": 640, "height": 480, "d": [], "k": K}))
    assert read_camera_file(ros2) == EXPECTED.undistorted()


def test_camera_calibration_yaml(tmp_path: Path) -> None:
    dev_dependency("yaml")
    path = tmp_path / "xtion.yaml"
    path.write_text(CALIBRATION_YAML)
    assert read_camera_file(path) == EXPECTED


def test_bad_camera_files(tmp_path: Path) -> None:
    fisheye = tmp_path / "fisheye.json"
    fisheye.write_text(json.dumps({"width": 640, "height": 480, "K": K, "D": [0.1, 0, 0, 0],
                                   "distortion_model": "equidistant"}))
    with pytest.raises(InputError, match="equidistant"):
        read_camera_file(fisheye)
    partial = tmp_path / "partial.json"
    partial.write_text(json.dumps({"K": K}))
    with pytest.raises(InputError, match="need fx"):
        read_camera_file(partial)
    broken = tmp_path / "broken.json"
    broken.write_text("{")
    with pytest.raises(SourceError, match="not valid JSON"):
        read_camera_file(broken)
    with pytest.raises(SourceError, match="cannot read"):
        read_camera_file(tmp_path / "missing.json")


def test_dataset_sources_carry_the_published_intrinsics(tmp_path: Path) -> None:
    tum = open_source(shared_path("data", "tum_fr2_desk"))
    camera = tum.camera()
    assert camera == DATASET_CAMERAS["tum_fr2"] and camera is not None
    np.testing.assert_allclose(
        [camera.fx, camera.fy, camera.cx, camera.cy], [520.9, 521.0, 325.1, 249.7]
    )
    assert camera.distortion == (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)
    fr3 = tmp_path / "rgbd_dataset_freiburg3_long_office_household"
    (fr3 / "rgb").mkdir(parents=True)
    (fr3 / "rgb" / "1.png").write_bytes(b"")
    (fr3 / "rgb.txt").write_text("1.0 rgb/1.png\n")
    assert open_source(fr3).camera() == DATASET_CAMERAS["tum_fr3"]
    (tmp_path / "seq-01").mkdir()
    (tmp_path / "seq-01" / "frame-000000.color.png").write_bytes(b"")
    assert SevenScenesSource(tmp_path / "seq-01").camera().fx == 585.0
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "0.png").write_bytes(b"")
    assert open_source(tmp_path / "plain").camera() is None

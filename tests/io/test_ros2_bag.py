"""ROS 2 bags (rosbags, MCAP) read back: every topic, the TF tree, poses through every conversion
(1e-9), stamps, unit quaternions, and pose jumps published in map -> odom only."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.errors import ConfigError, InputError
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.geometry.se3 import rotation_from_quat_xyzw
from kvtracker_sdk.io.exports.ros_frames import DEFAULT_T_BASE_OPTICAL, map_from_world
from kvtracker_sdk.types import FrameResult
from tests.helpers import dev_dependency
from tests.tracking.sim_session import SIZE, drive, make_tracker

rosbags = dev_dependency("rosbags")
from rosbags.highlevel import AnyReader  # noqa: E402

from kvtracker_sdk.io.exports.ros2_bag import TOPICS, stamp_ns, write_ros2_bag  # noqa: E402

POSE_TOL = 1e-9  # through quaternion, CDR float64 and back


@pytest.fixture(scope="module")
def run() -> tuple[list[FrameResult], Any]:
    """80 frames, keyframes every 20 (rebuilds), camera covered for frames 45-55 (relocalises).
    Timestamps are TUM-like (1.3e9 s) to exercise the nanosecond conversion."""
    truth = orbit(num_frames=80, turns=0.25)
    truth = type(truth)(truth.timestamps + 1311868169.16, truth.poses)
    backend = SimulatedBackend(truth, seed=3, loss_segments=[(45, 55)])
    with make_tracker(backend, keyframing={"interval_frames": 20}) as tracker:
        session = drive(tracker, backend, stop=80)
        return session.results, tracker.keyframe_map


def _read(path: Path) -> dict[str, list[tuple[int, Any]]]:
    messages: dict[str, list[tuple[int, Any]]] = {}
    with AnyReader([path]) as reader:
        for connection, time_ns, raw in reader.messages():
            message = reader.deserialize(raw, connection.msgtype)
            messages.setdefault(connection.topic, []).append((time_ns, message))
    return messages


def _matrix(translation: Any, rotation: Any) -> np.ndarray:
    quat = np.array([rotation.x, rotation.y, rotation.z, rotation.w])
    assert abs(np.linalg.norm(quat) - 1.0) < 1e-12, "quaternions are normalised"
    T = np.eye(4)
    T[:3, :3] = rotation_from_quat_xyzw(quat)
    T[:3, 3] = [translation.x, translation.y, translation.z]
    return T


@pytest.fixture(scope="module")
def bag(run: tuple[list[FrameResult], Any], tmp_path_factory: pytest.TempPathFactory) -> Path:
    results, keyframe_map = run
    path = tmp_path_factory.mktemp("ros") / "run_bag"
    write_ros2_bag(path, results, keyframe_map, image_size=(SIZE[1], SIZE[0]), path_every=7)
    return path


def test_every_topic_is_written_with_its_type(bag: Path) -> None:
    with AnyReader([bag]) as reader:
        found = {c.topic: c.msgtype for c in reader.connections}
        assert reader.connections[0].ext.serialization_format == "cdr"
    assert found == TOPICS
    assert (bag / f"{bag.name}.mcap").is_file()


def test_tf_tree_and_poses_compose_to_the_tracked_pose(
    bag: Path, run: tuple[list[FrameResult], Any]
) -> None:
    results, _ = run
    messages = _read(bag)
    (static_time, static), = messages["/tf_static"]
    (base_optical,) = static.transforms
    assert (base_optical.header.frame_id, base_optical.child_frame_id) == (
        "base_link", "camera_optical_frame")
    T_base_optical = _matrix(base_optical.transform.translation, base_optical.transform.rotation)
    np.testing.assert_allclose(T_base_optical, DEFAULT_T_BASE_OPTICAL, atol=POSE_TOL)

    valid = [r for r in results if r.pose_valid and r.pose is not None]
    tf = messages["/tf"]
    assert len(tf) == len(valid) and len(valid) < len(results)  # lost frames publish no TF
    for (time_ns, message), result in zip(tf, valid, strict=True):
        map_odom, odom_base = message.transforms
        assert (map_odom.header.frame_id, map_odom.child_frame_id) == ("map", "odom")
        assert (odom_base.header.frame_id, odom_base.child_frame_id) == ("odom", "base_link")
        assert result.timestamp is not None
        expected_ns = round(result.timestamp * 1e9)
        assert time_ns == expected_ns == stamp_ns(result.timestamp)
        stamp = map_odom.header.stamp
        assert stamp.sec * 10**9 + stamp.nanosec == expected_ns
        T_map_base = (_matrix(map_odom.transform.translation, map_odom.transform.rotation)
                      @ _matrix(odom_base.transform.translation, odom_base.transform.rotation))
        # map -> base_link -> camera_optical_frame is the tracked camera in the map frame
        T_map_camera = T_map_base @ T_base_optical
        expected = DEFAULT_T_BASE_OPTICAL @ result.pose.T_world_cam  # type: ignore[union-attr]
        np.testing.assert_allclose(T_map_camera, expected, atol=POSE_TOL)


def test_pose_jumps_go_into_map_to_odom_and_odom_stays_continuous(
    bag: Path, run: tuple[list[FrameResult], Any]
) -> None:
    results, _ = run
    tf = [m.transforms for _, m in _read(bag)["/tf"]]
    valid = [r for r in results if r.pose_valid]
    starts = [i for i in range(1, len(valid))
              if valid[i].frame_index != valid[i - 1].frame_index + 1
              or valid[i].map_generation != valid[i - 1].map_generation]
    assert starts, "the run has a relocalisation and rebuilds"
    relocalised = next(i for i in starts if valid[i].frame_index != valid[i - 1].frame_index + 1)
    for i in range(1, len(valid)):
        before = _matrix(tf[i - 1][1].transform.translation, tf[i - 1][1].transform.rotation)
        after = _matrix(tf[i][1].transform.translation, tf[i][1].transform.rotation)
        map_odom_before = _matrix(tf[i - 1][0].transform.translation, tf[i - 1][0].transform.rotation)
        map_odom_after = _matrix(tf[i][0].transform.translation, tf[i][0].transform.rotation)
        if i in starts:  # odom holds still across the jump
            np.testing.assert_allclose(after, before, atol=POSE_TOL)
        else:  # map -> odom is constant within a segment
            np.testing.assert_allclose(map_odom_after, map_odom_before, atol=POSE_TOL)
    jump = _matrix(tf[relocalised][0].transform.translation, tf[relocalised][0].transform.rotation)
    previous = _matrix(tf[relocalised - 1][0].transform.translation,
                       tf[relocalised - 1][0].transform.rotation)
    assert np.linalg.norm(jump[:3, 3] - previous[:3, 3]) > 1e-3  # the camera moved while lost


def test_odometry_path_camera_info_cloud_markers_and_diagnostics(
    bag: Path, run: tuple[list[FrameResult], Any]
) -> None:
    results, keyframe_map = run
    messages = _read(bag)
    valid = [r for r in results if r.pose_valid and r.pose is not None]
    odometry = [m for _, m in messages["/odom"]]
    assert len(odometry) == len(valid)
    for message, result in zip(odometry, valid, strict=True):
        assert (message.header.frame_id, message.child_frame_id) == ("odom", "base_link")
        variance = message.pose.covariance.reshape(6, 6)
        np.testing.assert_allclose(np.diag(variance)[0], (0.01 / result.confidence) ** 2,
                                   rtol=1e-12)
        assert np.count_nonzero(variance - np.diag(np.diag(variance))) == 0
    path = messages["/kvtracker/path"][-1][1]  # the last one holds the whole path
    assert path.header.frame_id == "map" and len(path.poses) == len(valid)
    last = path.poses[-1].pose
    np.testing.assert_allclose(
        _matrix(last.position, last.orientation),
        map_from_world(valid[-1].pose.T_world_cam, DEFAULT_T_BASE_OPTICAL),  # type: ignore[union-attr]
        atol=POSE_TOL)
    infos = [m for _, m in messages["/camera/camera_info"]]
    assert len(infos) == len(results)
    assert (infos[0].width, infos[0].height) == (SIZE[1], SIZE[0])
    assert infos[0].header.frame_id == "camera_optical_frame"
    K = infos[0].k.reshape(3, 3)
    assert K[0, 0] == pytest.approx(0.81 * SIZE[1], rel=1e-3)  # the simulated camera's focal
    assert (K[0, 2], K[1, 2]) == pytest.approx(((SIZE[1] - 1) / 2, (SIZE[0] - 1) / 2), abs=1e-6)
    cloud = messages["/kvtracker/map_points"][-1][1]
    assert cloud.header.frame_id == "map" and cloud.point_step == 16
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "rgb"]
    assert len(cloud.data) == cloud.width * 16 > 0
    markers = messages["/kvtracker/keyframes"][-1][1].markers
    assert markers[0].action == 3  # DELETEALL, then one frustum per keyframe
    assert [m.id for m in markers[1:]] == list(keyframe_map.keyframe_ids)
    diagnostics = [m.status[0] for _, m in messages["/diagnostics"]]
    assert len(diagnostics) == len(results)
    for status, result in zip(diagnostics, results, strict=True):
        assert status.message == f"{result.state.value} ({result.reason.value})"
        assert status.level == (0 if result.state.value == "TRACKING" else 1)
    assert {s.message.split()[0] for s in diagnostics} == {"TRACKING", "RELOCALIZING"}


def test_extrinsic_and_intrinsics_are_configurable(
    run: tuple[list[FrameResult], Any], tmp_path: Path
) -> None:
    results, keyframe_map = run
    T_base_optical = DEFAULT_T_BASE_OPTICAL.copy()
    T_base_optical[:3, 3] = [0.1, 0.0, 0.3]  # camera 10 cm ahead, 30 cm up
    camera = Camera(520.9, 521.0, 325.1, 249.7, 640, 480)
    write_ros2_bag(tmp_path / "bag", results[:30], keyframe_map, image_size=(640, 480),
                   T_base_optical=T_base_optical, intrinsics=camera)
    messages = _read(tmp_path / "bag")
    static = messages["/tf_static"][0][1].transforms[0].transform.translation
    assert (static.x, static.y, static.z) == (0.1, 0.0, 0.3)
    np.testing.assert_array_equal(messages["/camera/camera_info"][0][1].k.reshape(3, 3), camera.K())
    with pytest.raises(ConfigError, match="exists"):
        write_ros2_bag(tmp_path / "bag", results, keyframe_map, image_size=(640, 480))
    with pytest.raises(InputError, match="rigid"):
        write_ros2_bag(tmp_path / "bag2", results, keyframe_map, image_size=(640, 480),
                       T_base_optical=np.eye(4) * 2)
    assert not (tmp_path / "bag2").exists()

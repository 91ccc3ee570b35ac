"""A metric, gravity-aligned world: depth frames, known sizes, gravity readings (short runs of the
checks ``benchmarks/metric_world.py`` makes over the whole 100 s TUM trajectory)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks.metric_world import (
    Drive,
    ate,
    drive,
    object_backend,
    ros_map_up_errors_deg,
    run_mono,
    run_rgbd,
    scale_errors,
    up_errors_deg,
    world_units_per_metre,
)
from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import GroundTruth, orbit
from kvtracker_sdk.errors import DepthError, GravityError, InputError, MapFormatError, StateError
from kvtracker_sdk.geometry.pixel_transform import PixelTransform
from kvtracker_sdk.io.exports.ros_frames import DEFAULT_T_BASE_OPTICAL, map_from_world
from kvtracker_sdk.io.map_file.map_file import read_map_info
from kvtracker_sdk.io.map_file.map_format import metadata_digest
from kvtracker_sdk.tracking.core.frame_input import check_depth
from kvtracker_sdk.tracking.core.model_input import depth_to_model
from kvtracker_sdk.tracking.world.metric_scale import fit_depth_scale
from kvtracker_sdk.tracking.world.world_alignment import level_rotation
from kvtracker_sdk.world import MapWorld, ScaleSource, WorldAlignment
from tests.helpers import dev_dependency, shared_path
from tests.tracking.sim_session import SIZE, make_tracker

FRAMES = 150  # keyframes at 0, 50, 100; the map is saved and reloaded at frame 75
DEPTH_EVERY = 10  # depth only matters at keyframes; rendering it costs ~20 ms a frame


@pytest.fixture(scope="module")
def tum() -> GroundTruth:
    return GroundTruth.from_tum(shared_path("data", "tum_fr2_desk", "groundtruth.txt"))


@pytest.fixture(scope="module")
def rgbd_gravity(
    tum: GroundTruth, tmp_path_factory: pytest.TempPathFactory
) -> tuple[dict, Drive, object, Path]:
    folder = tmp_path_factory.mktemp("rgbd")
    row, run, kf_map = run_rgbd(tum, FRAMES, folder, gravity=True, reload_at=FRAMES // 2,
                                depth_every=DEPTH_EVERY)
    return row, run, kf_map, folder


# ---------------------------------------------------------------------------------- depth input
def test_depth_in_raw_units_or_metres_with_holes() -> None:
    raw = np.array([[0, 1000], [2500, 65535]], dtype=np.uint16)
    assert np.allclose(check_depth(raw, 0.001, (2, 2)), [[0, 1.0], [2.5, 65.535]])
    metres = np.array([[np.nan, 1.5], [np.inf, 0.0]], dtype=np.float32)
    assert check_depth(metres[..., None], None, (2, 2)).tolist() == [[0, 1.5], [0, 0]]


@pytest.mark.parametrize(("depth", "scale", "match"), [
    (np.ones((2, 3), np.float32), None, "does not match"),
    (np.ones((2, 2), np.uint16), None, "needs depth_scale"),
    (np.ones((2, 2), np.uint16), -1.0, "finite and > 0"),
    (np.ones((2, 2), np.uint16), "mm", "must be a number"),
    (-np.ones((2, 2), np.float32), None, "negative"),
    (-np.ones((2, 2), np.int32), 0.001, "negative"),
    (np.ones((2, 2), bool), 0.001, "bool"),
    (np.ones((2, 2), np.complex64), None, "dtype"),
    ([[1.0, 1.0], [1.0, 1.0]], None, "numpy array"),
])
def test_bad_depth_is_a_typed_error(depth: object, scale: object, match: str) -> None:
    with pytest.raises(DepthError, match=match):
        check_depth(depth, scale, (2, 2))


def test_depth_is_sampled_nearest_and_padding_is_a_hole() -> None:
    depth = np.arange(16, dtype=np.float32).reshape(4, 4)
    half = depth_to_model(depth, PixelTransform.resize((4, 4), (2, 2)), (2, 2))
    assert set(half.ravel().tolist()) <= set(depth.ravel().tolist())  # never a blend
    padded = depth_to_model(depth, PixelTransform.crop(-1, 0), (4, 6))  # one column of padding
    assert padded[:, 0].tolist() == [0, 0, 0, 0] and padded[:, 1].tolist() == depth[:, 0].tolist()


def test_bad_depth_or_gravity_leaves_the_tracker_untouched() -> None:
    backend = SimulatedBackend(orbit(10), seed=1)
    frames = list(backend.frames(SIZE, stop=2, textured=False))
    with make_tracker(backend) as tracker:
        with pytest.raises(DepthError):
            tracker.push_frame(frames[0].image, depth=np.ones((3, 3), np.float32))
        for gravity in ([0, 0], [0, np.nan, 1], [0, 0, 0], "down"):
            with pytest.raises(GravityError):
                tracker.push_frame(frames[0].image, gravity=gravity)
        assert tracker.keyframe_map is None and tracker.snapshot().frame_index is None
        assert tracker.push_frame(frames[0].image).frame_index == 0


# ---------------------------------------------------------------------------------- the estimator
def test_scale_fit_is_robust_to_outliers_and_follows_confidence() -> None:
    rng = np.random.default_rng(0)
    predicted = rng.uniform(0.5, 3.0, (64, 64)).astype(np.float32)
    sensor = (2.5 * predicted * (1 + 0.01 * rng.standard_normal(predicted.shape))).astype(np.float32)
    outliers = rng.random(predicted.shape) < 0.4  # flying pixels, shiny surfaces: 40 % wrong
    sensor[outliers] *= rng.uniform(0.2, 5.0, int(outliers.sum())).astype(np.float32)
    confidence = np.ones_like(predicted)
    fit = fit_depth_scale([sensor], [predicted], [confidence], [None], patch_size=14)
    assert fit is not None and fit.scale == pytest.approx(2.5, rel=0.02)  # a mean: off by ~50 %
    assert 0 < fit.relative_uncertainty < 0.05 and fit.patches <= 25
    # the same pixels with the network unsure where the sensor is wrong: closer still
    confidence[outliers] = 0.01
    weighted = fit_depth_scale([sensor], [predicted], [confidence], [None], patch_size=14)
    assert weighted is not None and abs(weighted.scale - 2.5) < abs(fit.scale - 2.5)
    assert weighted.scale == pytest.approx(2.5, rel=0.005)
    assert fit_depth_scale([None], [predicted], [confidence], [None], patch_size=14) is None


# ---------------------------------------------------------------------------------- depth runs
def test_depth_makes_the_world_metric_through_rebuilds_and_a_reload(
    tum: GroundTruth, rgbd_gravity: tuple[dict, Drive, object, Path]
) -> None:
    row, run, _, _ = rgbd_gravity
    mono = run_mono(tum, FRAMES)
    # the simulation is not metric by itself: its first map measures 0.2 units per metre
    assert abs(mono["world_units_per_metre"] - 1.0) > 0.5
    errors = scale_errors(run)
    assert errors["maps"] >= 3  # bootstrap, two rebuilds (one after the reload)
    assert errors["after_first_map"] <= 0.01 and errors["end"] <= 0.02 and errors["max"] <= 0.02
    # metres without any alignment scale: the same ATE as the scale-fitted mono run (5 %)
    assert row["ate_m_se3"] == pytest.approx(mono["ate_m_sim3"], rel=0.05)
    assert row["world"]["scale_source"] == "depth"
    assert WorldAlignment.METRIC_SCALE.value not in row["world_events"]  # metric from birth
    depth_estimate = row["scale_estimates"][0]
    assert depth_estimate["source"] == "depth"
    assert depth_estimate["metres_per_unit"] == pytest.approx(1.0, abs=1e-9)  # anchored
    assert 0 < depth_estimate["relative_uncertainty"] < 0.01


def test_gravity_levels_the_world_and_the_ros_map_frame(
    rgbd_gravity: tuple[dict, Drive, object, Path]
) -> None:
    row, run, kf_map, folder = rgbd_gravity
    assert row["up_error_deg_max_window"] <= 0.5
    assert row["heading_error_deg"] <= 1.0  # yaw stays keyframe 0's
    assert row["world"]["gravity_aligned"] is True
    assert WorldAlignment.GRAVITY.value in row["world_events"]
    # the reload kept the levelled world: no levelling from the new session's first readings
    reload_frame = FRAMES // 2
    assert not [e for e in run.world_events
                if e.frame_index is not None and reload_frame <= e.frame_index < reload_frame + 32]
    dev_dependency("rosbags")
    bag = ros_map_up_errors_deg(run, kf_map, folder)  # type: ignore[arg-type]
    assert bag["poses"] >= FRAMES - 10 and bag["map_up_error_deg_max_window"] <= 0.5


def test_without_depth_or_gravity_the_world_stays_as_it_was(tmp_path: Path) -> None:
    backend = SimulatedBackend(orbit(60), seed=1)
    run, tracker = drive(backend, frames=60, config={"keyframing": {"interval_frames": 20}})
    with tracker:
        status = tracker.map_status
        info = tracker.save_map(tmp_path / "plain.kvmap")
    assert run.world_events == [] and status.world == MapWorld()
    assert status.scale_estimates == () and status.gravity is None
    assert read_map_info(tmp_path / "plain.kvmap").world == MapWorld() == info.world
    header = (tmp_path / "plain.kvmap").read_bytes()[8:20000]
    assert b'"world"' not in header  # files stay as older SDKs wrote them
    # the map frame follows the camera's body axes as before
    T = run.results[-1].pose.T_world_cam  # type: ignore[union-attr]
    assert np.allclose(map_from_world(T, DEFAULT_T_BASE_OPTICAL),
                       DEFAULT_T_BASE_OPTICAL @ T @ np.linalg.inv(DEFAULT_T_BASE_OPTICAL))


def test_a_world_change_event_carries_the_transform_of_poses_and_points() -> None:
    backend = SimulatedBackend(orbit(40), seed=1)
    frames = list(backend.frames(SIZE, stop=2, textured=False))
    with make_tracker(backend) as tracker:
        events: list = []
        tracker.events.on_world_frame_changed(events.append)
        tracker.push_frame(frames[0].image)
        before = tracker.keyframe_map.keyframes[0]  # type: ignore[union-attr]
        tilted = np.array([0.3, 9.7, 0.5])  # not the camera's y: the world must turn
        tracker.push_frame(frames[1].image, gravity=tilted)
        after = tracker.keyframe_map.keyframes[0]  # type: ignore[union-attr]
        assert len(events) == 1 and events[0].reason is WorldAlignment.GRAVITY
        W = events[0].transform
        assert np.allclose(W.apply_to_pose(before.T_world_cam), after.T_world_cam)
        assert np.allclose(W.apply_to_points(before.world_points()), after.world_points(),
                           atol=1e-5)
        pose = tracker.get_pose()
        assert pose is not None and tracker.map_status.world.gravity_aligned
        up_in_camera = -tilted / np.linalg.norm(tilted)
        assert np.allclose(pose.T_world_cam[:3, :3] @ up_in_camera, [0, 0, 1], atol=1e-9)


def test_level_rotation_keeps_the_heading() -> None:
    up = np.array([0.0, -0.8, -0.6])  # a camera pitched down: world -y is up
    R = level_rotation(up, np.array([0.0, 0.0, 1.0]), np.array([0.0, -1.0, 0.0]))
    assert np.allclose(R @ up, [0, 0, 1]) and np.isclose(np.linalg.det(R), 1.0)
    forward = R @ np.array([0.0, 0.0, 1.0])
    assert abs(forward[1]) < 1e-12 and forward[0] > 0  # forward stays in the x-z plane
    looking_down = level_rotation(np.array([0.0, 0.0, -1.0]), np.array([0.0, 0.0, 1.0]),
                                  np.array([0.0, -1.0, 0.0]))  # forward is vertical: fallback
    assert np.allclose(looking_down @ np.array([0.0, -1.0, 0.0]), [1, 0, 0])


# ---------------------------------------------------------------------------------- known sizes
def test_a_known_distance_makes_the_world_metric(tum: GroundTruth) -> None:
    backend = SimulatedBackend(tum)
    truth = backend.ground_truth.poses
    run, tracker = drive(backend, frames=301)
    with tracker:
        with pytest.raises(InputError):
            tracker.world.set_known_distance(-1.0, [0, 0, 0], [1, 0, 0])
        with pytest.raises(InputError):
            tracker.world.set_known_distance(1.0, [0, 0, 0], [0, 0, 0])
        events: list = []
        tracker.events.on_world_frame_changed(events.append)
        first = run.results[0].pose
        last = tracker.get_tracked_pose()
        length = float(np.linalg.norm(truth[300, :3, 3] - truth[0, :3, 3]))  # 1.45 m
        tracker.world.set_known_distance(length, first, last)
        units = world_units_per_metre(backend, tracker.keyframe_map)  # type: ignore[arg-type]
        status = tracker.map_status
        pose = tracker.get_pose()
    # two tracked poses 1.45 m apart with 1 cm of noise per axis each: 1 % (1 sigma) of error
    assert abs(units - 1.0) <= 0.03
    assert len(events) == 1 and events[0].reason is WorldAlignment.METRIC_SCALE
    assert last is not None and pose is not None
    assert np.allclose(pose.translation, events[0].transform.apply_to_points(last.pose.translation))
    assert status.world.scale_source is ScaleSource.KNOWN_SIZE
    assert [e.source for e in status.scale_estimates] == [ScaleSource.KNOWN_SIZE]


def test_object_height_on_frame_zero() -> None:
    """A 0.5 m box on a 0.3 deg-noisy orbit, with accelerometer readings ("height" is along up),
    its height stated with the first frame (before there is a map: applied once there is)."""
    from kvtracker_sdk.backends.simulated_sensors import gravity_reading

    backend, height = object_backend("box")
    rng = np.random.default_rng(0)
    with make_tracker(backend, mode="object") as tracker:
        events: list = []
        tracker.events.on_world_frame_changed(events.append)
        tracker.world.set_object_height(height)
        for frame in backend.frames(SIZE, stop=8, textured=False, with_mask=True):
            tracker.push_frame(frame.image, mask=frame.mask,
                               gravity=gravity_reading(frame.T_world_cam, rng=rng))
        status = tracker.map_status
        units = world_units_per_metre(backend, tracker.keyframe_map)  # type: ignore[arg-type]
    assert [e.reason for e in events][:2] == [WorldAlignment.GRAVITY, WorldAlignment.METRIC_SCALE]
    assert abs(units - 1.0) <= 0.02
    assert status.world.scale_source is ScaleSource.KNOWN_SIZE and status.world.gravity_aligned
    with make_tracker(backend) as scene, pytest.raises(StateError):
        scene.world.set_object_height(0.5)


def test_a_known_size_is_only_checked_in_a_world_metric_by_depth(tum: GroundTruth) -> None:
    backend = SimulatedBackend(tum)
    run, tracker = drive(backend, frames=2, depth_every=1)
    with tracker:
        tracker.world.set_known_distance(1.0, [0, 0, 0], [0.5, 0, 0])  # 2 m per metre: wrong
        status = tracker.map_status
    assert run.world_events == [] and status.world.scale_source is ScaleSource.DEPTH
    known = [e for e in status.scale_estimates if e.source is ScaleSource.KNOWN_SIZE]
    assert len(known) == 1 and not known[0].applied and known[0].metres_per_unit == 2.0


# ---------------------------------------------------------------------------------- map files
def test_a_metric_levelled_map_says_so_and_older_maps_load(
    rgbd_gravity: tuple[dict, Drive, object, Path], tmp_path: Path
) -> None:
    _, _, _, folder = rgbd_gravity
    info = read_map_info(folder / "reload.kvmap")
    assert info.world.scale_source is ScaleSource.DEPTH and info.world.gravity_aligned
    assert info.world.scale_uncertainty is not None and info.world.gravity_uncertainty_deg
    data = (folder / "reload.kvmap").read_bytes()
    length = int.from_bytes(data[:8], "little")
    header = json.loads(data[8:8 + length])

    def rewritten(metadata: dict) -> Path:
        metadata = dict(metadata)
        metadata["metadata_sha256"] = metadata_digest(metadata)
        text = json.dumps({**header, "__metadata__": metadata}).encode()
        path = tmp_path / f"map{len(list(tmp_path.iterdir()))}.kvmap"
        # tensor offsets count from the header's end: a header of another length still fits
        path.write_bytes(len(text).to_bytes(8, "little") + text + data[8 + length:])
        return path

    older = {k: v for k, v in header["__metadata__"].items() if k != "world"}
    assert read_map_info(rewritten(older)).world == MapWorld()
    bad = {**header["__metadata__"], "world": json.dumps({"scale_source": "guess",
                                                          "gravity_aligned": False})}
    with pytest.raises(MapFormatError, match="scale_source"):
        read_map_info(rewritten(bad))


def test_up_error_measures_a_tilted_world() -> None:
    rng = np.random.default_rng(0)
    truth = np.tile(np.eye(4), (200, 1, 1))
    truth[:, :3, :3] = [np.linalg.qr(rng.standard_normal((3, 3)))[0] for _ in range(200)]
    truth[:, :3, :3] *= np.sign(np.linalg.det(truth[:, :3, :3]))[:, None, None]
    tilt = np.array([[1, 0, 0], [0, np.cos(0.01), -np.sin(0.01)], [0, np.sin(0.01), np.cos(0.01)]])
    estimated = truth.copy()
    estimated[:, :3, :3] = tilt @ truth[:, :3, :3]
    windows, median = up_errors_deg(estimated, truth)
    assert np.allclose(windows, np.degrees(0.01)) and median == pytest.approx(np.degrees(0.01))
    assert ate(estimated, estimated, with_scale=False) == pytest.approx(0.0, abs=1e-12)


def test_a_rebuild_in_flight_lands_in_the_levelled_world() -> None:
    from kvtracker_sdk.backends.simulated_sensors import gravity_reading
    from tests.tracking.gated_backend import GATE_TIMEOUT_S, GatedBackend

    backend = GatedBackend(orbit(40), seed=1)
    frames = list(backend.frames(SIZE, stop=13, textured=False))
    config = {"threading": {"async_mapping": True}, "keyframing": {"interval_frames": 10}}
    quiet = np.random.default_rng(0)
    with make_tracker(backend, **config) as tracker:
        tracker.push_frame(frames[0].image)
        assert tracker.wait_for_map(GATE_TIMEOUT_S)
        backend.hold(2)  # the rebuild adding frame 10
        for frame in frames[1:11]:
            tracker.push_frame(frame.image)
        assert backend.started(2) and tracker.map_status.rebuilding
        # levelled while that rebuild (started in the camera-0 world) is running
        tracker.push_frame(frames[11].image,
                           gravity=gravity_reading(frames[11].T_world_cam, rng=quiet, noise=0.0))
        levelled = tracker.keyframe_map
        assert levelled is not None and levelled.world.gravity_aligned
        backend.release(2)
        assert tracker.wait_for_map(GATE_TIMEOUT_S)
        tracker.push_frame(frames[12].image)
        rebuilt = tracker.keyframe_map
    assert rebuilt is not None and rebuilt.num_keyframes == 2
    assert rebuilt.generation > levelled.generation and rebuilt.world.gravity_aligned
    for keyframe in rebuilt.keyframes:  # both keyframes see the true up as the world's z
        true_up_in_camera = frames[keyframe.frame_index].T_world_cam[:3, :3].T @ [0, 0, 1]
        up = keyframe.T_world_cam[:3, :3] @ true_up_in_camera
        assert np.degrees(np.arccos(np.clip(up[2], -1, 1))) < 1.0  # pose noise 0.3 deg per axis


def test_rebuilds_of_a_depth_map_take_their_scale_from_the_sensor_not_the_last_map() -> None:
    from dataclasses import replace

    from kvtracker_sdk.backends.simulated_sensors import sensor_depth

    backend = SimulatedBackend(orbit(40), seed=1)
    config = {"keyframing": {"interval_frames": 10}}
    rng = np.random.default_rng(0)
    with make_tracker(backend, **config) as tracker:
        for frame in backend.frames(SIZE, stop=12, textured=False):
            depth = sensor_depth(backend.scene, frame.T_world_cam, SIZE, rng=rng)
            tracker.push_frame(frame.image, depth=depth if frame.index in (0, 10) else None)
            if frame.index == 0:  # a map whose depths drifted 10 % (what rebuilds would inherit)
                kf_map = tracker.keyframe_map
                assert kf_map is not None
                drifted = tuple(replace(kf, local_points=kf.local_points * np.float32(1.1))
                                for kf in kf_map.keyframes)
                tracker._keeper.map = replace(kf_map, keyframes=drifted)
        rebuilt = tracker.keyframe_map
    assert rebuilt is not None and rebuilt.num_keyframes == 2
    assert abs(world_units_per_metre(backend, rebuilt) - 1.0) < 0.01  # not 1.1


def test_live_frames_carry_their_depth_and_gravity() -> None:
    from kvtracker_sdk.backends.simulated_sensors import gravity_reading, sensor_depth

    backend = SimulatedBackend(orbit(20), seed=1)
    rng = np.random.default_rng(0)
    with make_tracker(backend) as tracker:
        for frame in backend.frames(SIZE, stop=3, textured=False):
            tracker.submit(frame.image, frame.timestamp,
                           depth=sensor_depth(backend.scene, frame.T_world_cam, SIZE, rng=rng),
                           depth_scale=1.0, gravity=gravity_reading(frame.T_world_cam, rng=rng))
            assert tracker.live.wait_idle(60.0)  # one at a time: none dropped
        world = tracker.map_status.world
        assert tracker.live.stats.processed == 3
    assert world.scale_source is ScaleSource.DEPTH and world.gravity_aligned


def test_depth_is_undistorted_like_its_colour_frame() -> None:
    from kvtracker_sdk.backends.simulated_scene import camera_matrix
    from kvtracker_sdk.geometry.camera import Camera
    from kvtracker_sdk.preprocess.undistort import Undistorter

    backend = SimulatedBackend(orbit(10), seed=1)
    frame = next(backend.frames(SIZE, stop=1, textured=False))
    camera = Camera.from_K(camera_matrix(SIZE), SIZE[1], SIZE[0], distortion=(0.25, -0.1, 0, 0))
    # depth = 1 m + 1 mm per column: undistortion moves columns, so it shows
    depth = (1.0 + 0.001 * np.arange(SIZE[1], dtype=np.float32))[None, :].repeat(SIZE[0], 0)
    with make_tracker(backend) as tracker:
        tracker.push_frame(frame.image, camera=camera, depth=depth)
        stored = tracker.keyframe_map.keyframes[0].sensor_depth  # type: ignore[union-attr]
    expected = Undistorter()(depth, camera, nearest=True)
    assert stored is not None and np.array_equal(stored, expected)  # model size = input size
    assert not np.array_equal(stored, depth)
    assert set(np.unique(stored)) <= set(np.unique(depth)) | {0.0}  # no blended depths

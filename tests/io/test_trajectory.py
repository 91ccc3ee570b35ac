"""TUM / KITTI trajectory files: the real TUM ground truth, round trips, malformed input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from kvtracker_sdk.errors import InputError, TrajectoryError
from kvtracker_sdk.io.files.trajectory import (
    Trajectory,
    read_kitti,
    read_trajectory,
    read_tum,
    write_kitti,
    write_tum,
)
from tests.helpers import shared_path

finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
stamp = st.floats(0.0, 2e9, allow_nan=False, allow_infinity=False)
quaternion = st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda q: np.linalg.norm(q) > 1e-3)


@st.composite
def trajectories(draw: st.DrawFn) -> Trajectory:
    n = draw(st.integers(0, 6))
    stamps = np.array(draw(st.lists(stamp, min_size=n, max_size=n)), dtype=np.float64)
    poses = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        poses[k, :3, :3] = Rotation.from_quat(draw(quaternion)).as_matrix()
        poses[k, :3, 3] = draw(st.tuples(finite, finite, finite))
    return Trajectory(stamps, poses)


def test_reads_the_real_tum_ground_truth() -> None:
    path = shared_path("data", "tum_fr2_desk", "groundtruth.txt")
    trajectory = read_tum(path)
    assert len(trajectory) == 20957  # 20,960 lines less the 3 comment lines
    # first data line: 1311868163.8697 -0.1357 -1.4217 1.4764 0.6453 -0.5498 0.3363 -0.4101
    assert trajectory.stamps[0] == 1311868163.8697
    np.testing.assert_array_equal(trajectory.positions[0], [-0.1357, -1.4217, 1.4764])
    expected = Rotation.from_quat([0.6453, -0.5498, 0.3363, -0.4101]).as_matrix()
    np.testing.assert_allclose(trajectory.poses[0, :3, :3], expected, atol=1e-12)
    assert np.all(np.diff(trajectory.stamps) >= 0)  # sorted (the file has one repeated stamp)
    # every rotation block is orthonormal although the file's quaternions have 4 digits
    gram = np.einsum("nji,njk->nik", trajectory.poses[:, :3, :3], trajectory.poses[:, :3, :3])
    np.testing.assert_allclose(gram, np.broadcast_to(np.eye(3), gram.shape), atol=1e-12)
    assert read_trajectory(path).stamps.tolist() == trajectory.stamps.tolist()


# Each example overwrites the same file, so sharing tmp_path across examples is harmless.
ROUND_TRIP = settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


@ROUND_TRIP
@given(trajectory=trajectories())
def test_tum_round_trip_keeps_stamps_and_positions_exactly(
    tmp_path: Path, trajectory: Trajectory
) -> None:
    path = tmp_path / "tum.txt"
    write_tum(path, trajectory)
    back = read_tum(path)
    assert back.stamps.tolist() == trajectory.stamps.tolist()  # bit-exact: written with repr
    np.testing.assert_array_equal(back.positions, trajectory.positions)
    np.testing.assert_allclose(back.poses[:, :3, :3], trajectory.poses[:, :3, :3], atol=1e-12)


@ROUND_TRIP
@given(trajectory=trajectories())
def test_kitti_round_trip_is_exact_and_numbers_the_poses(
    tmp_path: Path, trajectory: Trajectory
) -> None:
    path = tmp_path / "kitti.txt"
    write_kitti(path, trajectory)
    back = read_kitti(path)
    np.testing.assert_array_equal(back.poses, trajectory.poses)
    assert back.stamps.tolist() == list(range(len(trajectory)))
    if len(trajectory):
        assert read_trajectory(path).poses.tolist() == trajectory.poses.tolist()


def test_nanosecond_stamps_survive_the_round_trip(tmp_path: Path) -> None:
    stamps = np.array([1311868169.163498, 1700000000.123456789, 0.1 + 0.2])
    trajectory = Trajectory(stamps, np.tile(np.eye(4), (3, 1, 1)))
    write_tum(tmp_path / "t.txt", trajectory)
    text = (tmp_path / "t.txt").read_text()
    assert text.startswith("# timestamp tx ty tz qx qy qz qw")
    assert text.splitlines()[1].split()[0] == "1311868169.163498"
    assert read_tum(tmp_path / "t.txt").stamps.tolist() == stamps.tolist()


def test_comments_blank_lines_and_unnormalised_quaternions(tmp_path: Path) -> None:
    path = tmp_path / "t.txt"
    path.write_text("# a comment\n\n  1.0 1 2 3 0 0 0 2\n# another\n2.0\t4 5 6 0 0 1 1\n")
    trajectory = read_tum(path)
    assert trajectory.stamps.tolist() == [1.0, 2.0]
    np.testing.assert_allclose(
        trajectory.poses[0], np.array([[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    )
    np.testing.assert_allclose(
        trajectory.poses[1, :3, :3],
        Rotation.from_euler("z", 90, degrees=True).as_matrix(),
        atol=1e-12,
    )


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("1 2 3 4 5 6 7\n", ":1: 7 values, expected 8"),
        ("# c\n1 2 3 4 5 6 7 x\n", ":2: not a number"),
        ("1 2 3 4 0 0 0 0\n", ":1: zero quaternion"),
        ("1 2 3 nan 0 0 0 1\n", ":1: NaN or infinite"),
    ],
)
def test_malformed_tum_rows_name_the_line(tmp_path: Path, content: str, message: str) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(TrajectoryError, match=message):
        read_tum(path)


def test_read_trajectory_rejects_other_widths_and_missing_files(tmp_path: Path) -> None:
    path = tmp_path / "t.txt"
    path.write_text("1 2 3\n")
    with pytest.raises(TrajectoryError, match="3 columns"):
        read_trajectory(path)
    path.write_text("# only a comment\n")
    with pytest.raises(TrajectoryError, match="no poses"):
        read_trajectory(path)
    with pytest.raises(TrajectoryError, match="cannot read"):
        read_tum(tmp_path / "missing.txt")
    assert issubclass(TrajectoryError, InputError)


def test_kitti_accepts_caller_stamps(tmp_path: Path) -> None:
    path = tmp_path / "k.txt"
    path.write_text("1 0 0 5 0 1 0 6 0 0 1 7\n1 0 0 8 0 1 0 9 0 0 1 10\n")
    trajectory = read_kitti(path, stamps=np.array([0.5, 0.75]))
    assert trajectory.stamps.tolist() == [0.5, 0.75]
    assert trajectory.positions.tolist() == [[5, 6, 7], [8, 9, 10]]
    with pytest.raises(TrajectoryError, match="3 stamps but 2 poses"):
        read_kitti(path, stamps=np.zeros(3))


def test_trajectory_validates_and_is_read_only() -> None:
    with pytest.raises(TrajectoryError, match=r"\[N, 4, 4\]"):
        Trajectory(np.zeros(2), np.zeros((2, 3, 4)))
    with pytest.raises(TrajectoryError, match="1-D"):
        Trajectory(np.float64(1.0), np.eye(4))
    with pytest.raises(TrajectoryError, match="finite"):
        Trajectory(np.array([np.nan]), np.eye(4)[None])
    poses = np.tile(np.eye(4), (3, 1, 1))
    trajectory = Trajectory(np.arange(3.0), poses)
    poses[0, 0, 3] = 9.0  # the trajectory copied its input
    assert trajectory.poses[0, 0, 3] == 0.0
    with pytest.raises(ValueError):
        trajectory.stamps[0] = 1.0
    assert trajectory.select([2, 0]).stamps.tolist() == [2.0, 0.0]
    assert len(Trajectory([], [])) == 0

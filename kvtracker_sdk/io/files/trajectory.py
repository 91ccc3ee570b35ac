"""Camera trajectories and their two common text formats, TUM and KITTI.

A :class:`Trajectory` is a time-stamped sequence of ``T_world_cam`` poses (camera-to-world, 4x4,
float64). On disk:

- **TUM** (``timestamp tx ty tz qx qy qz qw``, one pose a line, quaternion scalar-last, ``#``
  comment lines): the format of the TUM RGB-D benchmark, evo and most SLAM systems. Stamps are
  written with ``repr`` (the shortest string that reads back to the same float64), so any
  stamp, e.g. ``1311868169.163498``, survives a round trip bit for bit (``%.6f`` would not
  for a nanosecond clock; ``%f`` drops digits).
- **KITTI** (12 numbers a line: the top 3x4 of the pose matrix, row-major): no stamps in the
  file; readers number the poses 0, 1, 2, ... unless the caller passes stamps.

Written by hand rather than taken from evo (GPL-3, a development dependency only); the parsing
is a few lines and reports the file and line of any malformed row.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import TypeAlias

import numpy as np

from kvtracker_sdk.errors import TrajectoryError
from kvtracker_sdk.geometry.se3 import quat_xyzw_from_rotation, rotation_from_quat_xyzw
from kvtracker_sdk.io.files.atomic import atomic_write
from kvtracker_sdk.user_files import read_user_text

__all__ = [
    "Trajectory",
    "read_kitti",
    "read_trajectory",
    "read_tum",
    "write_kitti",
    "write_tum",
]

# ~600k TUM lines (hours of 100 Hz motion capture); parsing costs several times the file's size,
# so a larger (or endless: /dev/zero behind a symlink) file is refused before it is read
MAX_TRAJECTORY_BYTES = 64 << 20
_TUM_COLUMNS = 8
_KITTI_COLUMNS = 12
PathLike: TypeAlias = "str | os.PathLike[str]"
_TUM_HEADER = "# timestamp tx ty tz qx qy qz qw  (T_world_cam, quaternion scalar-last)"


@dataclass(frozen=True)
class Trajectory:
    """Stamped camera poses.

    ``stamps``: [N] float64 seconds. ``poses``: [N, 4, 4] float64 ``T_world_cam`` (camera-to-world,
    OpenCV camera axes). Both are copied and made read-only; N may be 0.
    """

    stamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        stamps = np.array(self.stamps, dtype=np.float64, copy=True)
        poses = np.array(self.poses, dtype=np.float64, copy=True)
        if stamps.ndim != 1:
            raise TrajectoryError(f"stamps must be a 1-D array, got shape {stamps.shape}")
        if len(stamps) == 0 and poses.size == 0:
            poses = poses.reshape(0, 4, 4)  # Trajectory([], []) is a valid empty trajectory
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise TrajectoryError(f"poses must have shape [N, 4, 4], got {poses.shape}")
        if len(stamps) != len(poses):
            raise TrajectoryError(f"{len(stamps)} stamps but {len(poses)} poses")
        if not (np.all(np.isfinite(stamps)) and np.all(np.isfinite(poses))):
            raise TrajectoryError("stamps and poses must be finite (found NaN or inf)")
        stamps.setflags(write=False)
        poses.setflags(write=False)
        object.__setattr__(self, "stamps", stamps)
        object.__setattr__(self, "poses", poses)

    def __len__(self) -> int:
        return len(self.stamps)

    @property
    def positions(self) -> np.ndarray:
        """Camera centres in the world frame, [N, 3]."""
        return self.poses[:, :3, 3]

    def select(self, indices: np.ndarray | list[int]) -> Trajectory:
        """The poses at ``indices`` (an integer index array), in that order."""
        idx = np.asarray(indices, dtype=np.intp)
        return Trajectory(self.stamps[idx], self.poses[idx])


def read_tum(path: PathLike) -> Trajectory:
    """Read a TUM trajectory file (``timestamp tx ty tz qx qy qz qw``; ``#`` lines skipped).

    Quaternions need not be exactly unit (they are normalised). Raises
    :class:`~kvtracker_sdk.errors.TrajectoryError` naming the file and line of a bad row.
    """
    return _parse_tum(path, _data_lines(path))


def read_kitti(path: PathLike, stamps: np.ndarray | None = None) -> Trajectory:
    """Read a KITTI pose file (12 numbers a line: the 3x4 top of ``T_world_cam``, row-major).

    ``stamps`` ([N] seconds) is attached to the poses; by default they are numbered 0, 1, 2, ...
    """
    return _parse_kitti(path, _data_lines(path), stamps)


def read_trajectory(path: PathLike) -> Trajectory:
    """Read a TUM or KITTI file, told apart by the number of columns (8 or 12)."""
    lines = _data_lines(path)
    if not lines:
        raise TrajectoryError(f"{path}: no poses (only blank or comment lines)")
    columns = len(lines[0][1])
    if columns == _KITTI_COLUMNS:
        return _parse_kitti(path, lines, None)
    if columns == _TUM_COLUMNS:
        return _parse_tum(path, lines)
    raise TrajectoryError(
        f"{path}: {columns} columns; expected 8 (TUM: timestamp tx ty tz qx qy qz qw) "
        "or 12 (KITTI: a 3x4 pose)"
    )


def write_tum(path: PathLike, trajectory: Trajectory, *, header: bool = True) -> None:
    """Write ``trajectory`` in TUM format, atomically, every number with full float64 precision.

    The quaternion is taken from each rotation block with ``w >= 0``; a comment line naming
    the columns comes first unless ``header`` is False.
    """
    rows = np.zeros((len(trajectory), _TUM_COLUMNS))
    if len(trajectory):
        rows[:, 0] = trajectory.stamps
        rows[:, 1:4] = trajectory.positions
        rows[:, 4:8] = quat_xyzw_from_rotation(trajectory.poses[:, :3, :3])
    with atomic_write(path) as handle:
        if header:
            handle.write(_TUM_HEADER + "\n")
        for row in rows:
            handle.write(" ".join(repr(float(v)) for v in row) + "\n")


def write_kitti(path: PathLike, trajectory: Trajectory) -> None:
    """Write ``trajectory`` in KITTI format (no stamps, no header), atomically, full precision."""
    with atomic_write(path) as handle:
        for pose in trajectory.poses:
            handle.write(" ".join(repr(float(v)) for v in pose[:3, :].ravel()) + "\n")


def _data_lines(path: PathLike) -> list[tuple[int, list[str]]]:
    """(line number, fields) of every non-blank, non-comment line."""
    # a FIFO or a device would block or never end: only a regular file is read, up to a cap
    text = read_user_text(path, TrajectoryError, what="trajectory file",
                          max_bytes=MAX_TRAJECTORY_BYTES)
    lines = []
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            lines.append((number, stripped.split()))
    return lines


def _to_array(
    path: PathLike, lines: list[tuple[int, list[str]]], columns: int, name: str
) -> np.ndarray:
    """The data lines as a float64 [N, columns] array; a bad row raises with its line number."""
    values = []
    for number, fields in lines:
        if len(fields) != columns:
            raise TrajectoryError(
                f"{path}:{number}: {len(fields)} values, expected {columns} for {name}"
            )
        try:
            row = [float(f) for f in fields]
        except ValueError as exc:
            raise TrajectoryError(f"{path}:{number}: not a number ({exc})") from exc
        if not all(np.isfinite(row)):
            raise TrajectoryError(f"{path}:{number}: NaN or infinite value")
        values.append(row)
    return np.array(values, dtype=np.float64).reshape(-1, columns)


def _parse_tum(path: PathLike, lines: list[tuple[int, list[str]]]) -> Trajectory:
    rows = _to_array(path, lines, _TUM_COLUMNS, "TUM (timestamp tx ty tz qx qy qz qw)")
    zero_quat = np.linalg.norm(rows[:, 4:8], axis=1) < 1e-12
    if np.any(zero_quat):
        raise TrajectoryError(f"{path}:{lines[int(np.argmax(zero_quat))][0]}: zero quaternion")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    if len(rows):
        poses[:, :3, :3] = rotation_from_quat_xyzw(rows[:, 4:8])
        poses[:, :3, 3] = rows[:, 1:4]
    return _build(path, rows[:, 0], poses)


def _parse_kitti(
    path: PathLike, lines: list[tuple[int, list[str]]], stamps: np.ndarray | None
) -> Trajectory:
    rows = _to_array(path, lines, _KITTI_COLUMNS, "KITTI (12 numbers: a 3x4 pose, row-major)")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    if stamps is None:
        stamps = np.arange(len(poses), dtype=np.float64)
    return _build(path, stamps, poses)


def _build(path: PathLike, stamps: np.ndarray, poses: np.ndarray) -> Trajectory:
    try:
        return Trajectory(stamps, poses)
    except TrajectoryError as exc:
        raise TrajectoryError(f"{path}: {exc}") from exc

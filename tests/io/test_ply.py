"""PLY point clouds: read back with plyfile (a standard reader) and with a strict byte check."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kvtracker_sdk.errors import InputError
from kvtracker_sdk.io.exports.ply import write_ply
from tests.helpers import dev_dependency


def _cloud(n: int = 500) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(7)
    points = rng.normal(scale=3.0, size=(n, 3))
    colors = rng.integers(0, 256, size=(n, 3), dtype=np.uint8)
    confidence = rng.uniform(0.0, 10.0, size=n)
    return points, colors, confidence


def test_plyfile_reads_points_colours_and_scalars(tmp_path: Path) -> None:
    plyfile = dev_dependency("plyfile")
    points, colors, confidence = _cloud()
    path = write_ply(tmp_path / "cloud.ply", points, colors, scalars={"confidence": confidence})
    data = plyfile.PlyData.read(str(path))
    assert not data.text and data.byte_order == "<"
    vertex = data["vertex"]
    assert vertex.count == len(points)
    assert [p.name for p in vertex.properties] == [
        "x",
        "y",
        "z",
        "red",
        "green",
        "blue",
        "confidence",
    ]
    xyz = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1)
    np.testing.assert_allclose(xyz, points, rtol=1e-6)  # stored as float32
    rgb = np.stack([vertex["red"], vertex["green"], vertex["blue"]], axis=1)
    np.testing.assert_array_equal(rgb, colors)
    np.testing.assert_allclose(vertex["confidence"], confidence, rtol=1e-6)


def test_bytes_follow_the_ply_specification_exactly(tmp_path: Path) -> None:
    """An independent parser: exact header, then N records of 3 float32 + 3 uchar, LE."""
    points, colors, _ = _cloud(10)
    path = write_ply(tmp_path / "c.ply", points, colors, comment="made\nby a test")
    raw = path.read_bytes()
    header_end = raw.index(b"end_header\n") + len(b"end_header\n")
    assert raw[:header_end].decode("ascii").splitlines() == [
        "ply",
        "format binary_little_endian 1.0",
        "comment made by a test",
        "element vertex 10",
        "property float x",
        "property float y",
        "property float z",
        "property uchar red",
        "property uchar green",
        "property uchar blue",
        "end_header",
    ]
    record = np.dtype([("xyz", "<f4", 3), ("rgb", "u1", 3)])
    assert len(raw) - header_end == 10 * record.itemsize == 150
    body = np.frombuffer(raw[header_end:], dtype=record)
    np.testing.assert_array_equal(body["xyz"], points.astype(np.float32))
    np.testing.assert_array_equal(body["rgb"], colors)


def test_float_colours_and_empty_clouds(tmp_path: Path) -> None:
    plyfile = dev_dependency("plyfile")
    path = write_ply(
        tmp_path / "f.ply", np.zeros((2, 3)), np.array([[0.0, 0.5, 1.0], [1.0, 0.0, 0.2]])
    )
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    assert vertex["red"].tolist() == [0, 255] and vertex["green"].tolist() == [128, 0]
    assert vertex["blue"].tolist() == [255, 51]
    empty = plyfile.PlyData.read(str(write_ply(tmp_path / "e.ply", np.zeros((0, 3)))))
    assert empty["vertex"].count == 0


@pytest.mark.parametrize(
    ("points", "colors", "scalars", "message"),
    [
        (np.zeros((4, 2)), None, None, r"\[N, 3\]"),
        (np.array([[0.0, np.nan, 0.0]]), None, None, "1 points are NaN"),
        (np.zeros((2, 3)), np.zeros((3, 3), np.uint8), None, r"shape \[2, 3\]"),
        (np.zeros((1, 3)), np.array([[0.0, 1.5, 0.0]]), None, r"\[0, 1\]"),
        (np.zeros((1, 3)), np.array([[1, 2, 3]], dtype=np.int64), None, "uint8 or floats"),
        (np.zeros((1, 3)), None, {"red": np.zeros(1)}, "identifier other than"),
        (np.zeros((1, 3)), None, {"bad name": np.zeros(1)}, "identifier"),
        (np.zeros((2, 3)), None, {"confidence": np.zeros(3)}, r"\[2\] array"),
    ],
)
def test_bad_inputs_raise_typed_errors_and_write_nothing(
    tmp_path: Path,
    points: np.ndarray,
    colors: np.ndarray | None,
    scalars: dict | None,
    message: str,
) -> None:
    with pytest.raises(InputError, match=message):
        write_ply(tmp_path / "bad.ply", points, colors, scalars=scalars)
    assert list(tmp_path.iterdir()) == []

"""Map exports: the fused point cloud (filters, colours, voxel dedup, PLY) and the TUM trajectory."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from kvtracker_sdk.errors import InputError
from kvtracker_sdk.io.exports.map_export import (
    export_keyframe_trajectory,
    export_point_cloud,
    fused_point_cloud,
)
from kvtracker_sdk.io.files.trajectory import read_tum
from tests.io.map_factory import make_map


def read_ply(path: Path) -> np.ndarray:
    """The vertex array of a binary little-endian PLY with float/uchar properties."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    assert header[1] == "format binary_little_endian 1.0"
    types = {"float": "<f4", "uchar": "u1"}
    fields = [
        (line.split()[2], types[line.split()[1]]) for line in header if line.startswith("property")
    ]
    return np.frombuffer(data[end:], dtype=fields)


def test_without_filters_every_pixel_is_exported_in_the_world_frame() -> None:
    keyframe_map = make_map()
    points, colors, confidence = fused_point_cloud(
        keyframe_map, min_confidence=0.0, use_masks=False
    )
    expected = np.concatenate([kf.world_points().reshape(-1, 3) for kf in keyframe_map.keyframes])
    np.testing.assert_allclose(points, expected, rtol=0, atol=1e-12)
    assert np.array_equal(
        colors, np.concatenate([kf.image.reshape(-1, 3) for kf in keyframe_map.keyframes])
    )
    assert confidence.shape == (len(points),)


def test_confidence_and_masks_select_pixels() -> None:
    keyframe_map = make_map()
    points, _, confidence = fused_point_cloud(keyframe_map, min_confidence=0.3)
    expected = sum(
        int(np.count_nonzero((kf.confidence_map >= 0.3) & (True if kf.mask is None else kf.mask)))
        for kf in keyframe_map.keyframes
    )
    assert len(points) == expected and confidence.min() >= 0.3


def test_voxel_filter_keeps_the_most_confident_point_per_voxel() -> None:
    keyframe_map = make_map()
    _, _, all_conf = fused_point_cloud(keyframe_map, min_confidence=0.0, use_masks=False)
    points, _, conf = fused_point_cloud(
        keyframe_map, min_confidence=0.0, use_masks=False, voxel_size=1e6
    )
    assert len(points) <= 8  # the cloud spans at most the 8 voxels around the origin
    assert conf.max() == all_conf.max()
    fine, _, _ = fused_point_cloud(
        keyframe_map, min_confidence=0.0, use_masks=False, voxel_size=0.5
    )
    voxels = np.floor(fine / 0.5).astype(np.int64)
    assert len(np.unique(voxels, axis=0)) == len(fine) < len(all_conf)


def test_non_finite_points_are_dropped() -> None:
    keyframe_map = make_map(num_keyframes=1)
    kf = keyframe_map.keyframes[0]
    points = kf.local_points.copy()
    points[0, 0] = np.inf
    broken = replace(keyframe_map, keyframes=(replace(kf, local_points=points),))
    out, _, _ = fused_point_cloud(broken, min_confidence=0.0, use_masks=False)
    assert len(out) == kf.image.shape[0] * kf.image.shape[1] - 1 and np.all(np.isfinite(out))


@pytest.mark.parametrize(
    "kwargs", [{"min_confidence": 1.5}, {"voxel_size": 0.0}, {"voxel_size": np.nan}]
)
def test_bad_filter_values_are_input_errors(kwargs: dict[str, float]) -> None:
    with pytest.raises(InputError):
        fused_point_cloud(make_map(), **kwargs)


def test_point_cloud_ply_holds_points_colours_and_confidence(tmp_path: Path) -> None:
    keyframe_map = make_map()
    count = export_point_cloud(keyframe_map, tmp_path / "cloud.ply", min_confidence=0.5)
    points, colors, confidence = fused_point_cloud(keyframe_map, min_confidence=0.5)
    vertices = read_ply(tmp_path / "cloud.ply")
    assert count == len(vertices) == len(points) > 0
    xyz = np.stack([vertices["x"], vertices["y"], vertices["z"]], axis=1)
    np.testing.assert_array_equal(xyz, points.astype(np.float32))  # PLY stores float32
    assert np.array_equal(
        np.stack([vertices["red"], vertices["green"], vertices["blue"]], axis=1), colors
    )
    np.testing.assert_array_equal(vertices["confidence"], confidence)


def test_trajectory_round_trips_through_tum(tmp_path: Path) -> None:
    keyframe_map = make_map(num_keyframes=4)  # keyframe 1 has no timestamp: frame indices used
    assert export_keyframe_trajectory(keyframe_map, tmp_path / "kf.txt") == 4
    trajectory = read_tum(tmp_path / "kf.txt")
    np.testing.assert_array_equal(trajectory.stamps, [0.0, 10.0, 20.0, 30.0])
    np.testing.assert_allclose(trajectory.poses, keyframe_map.poses(), rtol=0, atol=1e-12)


def test_trajectory_uses_timestamps_sorted_by_time(tmp_path: Path) -> None:
    base = make_map(num_keyframes=3)
    stamps = [5.25, 1311868164.363181, 2.5]
    keyframes = tuple(
        replace(kf, timestamp=t) for kf, t in zip(base.keyframes, stamps, strict=True)
    )
    export_keyframe_trajectory(replace(base, keyframes=keyframes), tmp_path / "kf.txt")
    trajectory = read_tum(tmp_path / "kf.txt")
    order = np.argsort(stamps)
    np.testing.assert_array_equal(trajectory.stamps, np.array(stamps)[order])  # exact: repr'd
    np.testing.assert_allclose(trajectory.poses, base.poses()[order], rtol=0, atol=1e-12)

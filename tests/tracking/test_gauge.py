"""Gauge: Sim(3) between mapping passes from shared keyframes (poses + depths)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kvtracker_sdk.cache.keyframe_map import Keyframe
from kvtracker_sdk.geometry.se3 import check_rigid
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.tracking.core.gauge import (
    anchor_gauge,
    depth_scale,
    estimate_gauge,
    keyframe_corrections,
)


def _random_sim3(seed: int) -> Sim3:
    rng = np.random.default_rng(seed)
    return Sim3(
        Rotation.random(random_state=seed).as_matrix(),
        rng.normal(size=3),
        float(rng.uniform(0.2, 5)),
    )


def _random_poses(count: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, :3] = Rotation.random(count, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.normal(size=(count, 3))
    return poses


def test_anchor_puts_keyframe_zero_at_identity() -> None:
    raw = _random_poses(1, 3)[0]
    np.testing.assert_allclose(anchor_gauge(raw).apply_to_pose(raw), np.eye(4), atol=1e-12)
    assert anchor_gauge(raw).scale == 1.0


@pytest.mark.parametrize("shared", [1, 2, 6])
def test_exact_recovery_from_shared_keyframes(shared: int) -> None:
    """World = S(raw) exactly: one shared keyframe is enough (scale from its depth map)."""
    truth = _random_sim3(shared)
    raw_poses = _random_poses(shared, 10 + shared)
    world_poses = truth.apply_to_pose(raw_poses)
    rng = np.random.default_rng(shared)
    raw_points = rng.uniform(0.5, 4.0, size=(shared, 16, 16, 3)).astype(np.float32)
    world_points = raw_points * np.float32(truth.scale)
    scale = depth_scale(list(world_points), list(raw_points), [None] * shared)
    gauge = estimate_gauge(world_poses, raw_poses, scale)
    assert gauge.scale == pytest.approx(truth.scale, rel=1e-6)  # float32 depths
    np.testing.assert_allclose(gauge.matrix(), truth.matrix(), atol=1e-5 * max(1.0, truth.scale))


def test_scale_is_a_median_robust_to_outlier_pixels() -> None:
    rng = np.random.default_rng(0)
    raw = rng.uniform(1.0, 3.0, size=(1, 40, 40, 3))
    world = raw * 2.5
    world[0, :8, :, 2] = 1000.0  # 20 % garbage depth in the previous map
    mask = np.ones((40, 40), dtype=bool)
    assert depth_scale(list(world), list(raw), [mask]) == pytest.approx(2.5, rel=1e-9)


def test_scale_ignores_pixels_outside_the_mask_and_invalid_depth() -> None:
    raw = np.ones((1, 8, 8, 3))
    world = np.full((1, 8, 8, 3), 3.0)
    world[0, :, :4, 2] = 7.0  # outside the mask
    world[0, 0, 4, 2] = np.nan
    mask = np.zeros((8, 8), dtype=bool)
    mask[:, 4:] = True
    assert depth_scale(list(world), list(raw), [mask], stride=1) == 3.0
    assert depth_scale(list(world * 0), list(raw), [None], stride=1) == 1.0  # nothing usable


def test_noisy_shared_poses_average_out() -> None:
    """Rotation noise of 1 deg per keyframe: the chordal mean is better than any single one."""
    truth = _random_sim3(7)
    raw = _random_poses(20, 8)
    world = truth.apply_to_pose(raw)
    noisy = raw.copy()
    noisy[:, :3, :3] = (
        noisy[:, :3, :3]
        @ Rotation.from_rotvec(
            np.random.default_rng(1).normal(scale=np.radians(1.0), size=(20, 3))
        ).as_matrix()
    )
    gauge = estimate_gauge(world, noisy, truth.scale)
    error = np.degrees(Rotation.from_matrix(gauge.rotation @ truth.rotation.T).magnitude())
    assert error < 0.5  # ~1 deg / sqrt(20) expected


def _kf(keyframe_id: int, pose: np.ndarray) -> Keyframe:
    zeros = np.zeros((2, 2), dtype=np.float32)
    return Keyframe(
        keyframe_id,
        0,
        None,
        np.zeros((2, 2, 3), np.uint8),
        None,
        pose,
        zeros,
        np.zeros((2, 2, 3), np.float32),
        1.0,
    )


def test_corrections_report_how_shared_keyframes_moved() -> None:
    old_pose = np.eye(4)
    new_pose = np.eye(4)
    new_pose[:3, :3] = Rotation.from_euler("z", 3, degrees=True).as_matrix()
    new_pose[:3, 3] = [0.1, 0.0, 0.0]
    correction = keyframe_corrections(
        [_kf(0, old_pose), _kf(5, old_pose)], [_kf(0, new_pose), _kf(9, old_pose)]
    )
    assert set(correction.transforms) == {0}  # keyframe 5 was evicted, 9 is new
    np.testing.assert_allclose(correction.transforms[0] @ old_pose, new_pose, atol=1e-12)
    assert check_rigid(correction.transforms[0])
    assert correction.max_translation == pytest.approx(0.1)
    assert correction.max_rotation_deg == pytest.approx(3.0)

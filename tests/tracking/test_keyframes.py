"""Keyframe policies: scene interval, object view angles, budget and eviction."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kvtracker_sdk.backends.simulated_scene import look_at
from kvtracker_sdk.cache.keyframe_map import Keyframe
from kvtracker_sdk.config import BudgetConfig, ObjectKeyframeRule
from kvtracker_sdk.tracking.mapping.keyframes import (
    KeyframeBudget,
    angle_difference_deg,
    interval_elapsed,
    novel_object_view,
    novel_view,
    novel_view_direction,
    object_centre,
    view_angles_deg,
)

UP = np.array([0.0, -1.0, 0.0])  # world = keyframe 0's camera frame (OpenCV): up is -y


def _keyframe(
    keyframe_id: int, pose: np.ndarray, *, depth: float = 2.0, mask: np.ndarray | None = None,
    focal: float | None = None,
) -> Keyframe:
    """An 8x8 keyframe at constant ``depth``; with ``focal``, points on a pinhole's rays (centre
    at pixel 3.5), else all on the optical axis."""
    size = (8, 8)
    points = np.zeros((*size, 3), dtype=np.float32)
    points[..., 2] = depth
    if focal is not None:
        offsets = (np.arange(8) - 3.5) / focal * depth
        points[..., 0], points[..., 1] = offsets[None, :], offsets[:, None]
    return Keyframe(
        keyframe_id=keyframe_id,
        frame_index=10 * keyframe_id,
        timestamp=None,
        image=np.zeros((*size, 3), dtype=np.uint8),
        mask=mask,
        T_world_cam=pose,
        confidence_map=np.ones(size, dtype=np.float32),
        local_points=points,
        mean_confidence=1.0,
    )


def _camera_at(azimuth_deg: float, elevation_deg: float, radius: float = 2.0) -> np.ndarray:
    """A camera on a sphere around the origin, looking at it (angles in the world convention)."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    centre = radius * np.array([np.cos(el) * np.sin(az), -np.sin(el), np.cos(el) * np.cos(az)])
    return look_at(centre, np.zeros(3), UP)


def test_interval_rule() -> None:
    assert not interval_elapsed(49, 0, 50)
    assert interval_elapsed(50, 0, 50)
    assert interval_elapsed(120, 60, 50)


@pytest.mark.parametrize(
    ("azimuth", "elevation"), [(0, 0), (90, 0), (-90, 30), (179, -45), (45, 80)]
)
def test_view_angles_recover_the_camera_placement(azimuth: float, elevation: float) -> None:
    got = view_angles_deg(_camera_at(azimuth, elevation), np.zeros(3))
    assert got == pytest.approx((azimuth, elevation), abs=1e-9)


def test_angle_difference_wraps_around() -> None:
    assert angle_difference_deg(179.0, -179.0) == pytest.approx(2.0)
    assert angle_difference_deg(-10.0, 350.0) == pytest.approx(0.0)
    assert angle_difference_deg(0.0, 180.0) == pytest.approx(180.0)


def test_novel_view_uses_min_over_keyframes_and_the_threshold() -> None:
    keyframes = np.stack([_camera_at(0, 0), _camera_at(40, 0)])
    centre = np.zeros(3)
    assert not novel_view(_camera_at(5, 5), keyframes, centre, 10.0)
    assert novel_view(_camera_at(20, 0), keyframes, centre, 10.0)  # 20 deg from both in azimuth
    assert novel_view(_camera_at(2, 15), keyframes, centre, 10.0)  # elevation alone suffices
    assert not novel_view(_camera_at(35, 9), keyframes, centre, 10.0)  # 5 deg from keyframe 2
    assert novel_view(_camera_at(-20, 0), keyframes, centre, 10.0)


def test_view_direction_rule_measures_the_angle_between_views() -> None:
    keyframes = np.stack([_camera_at(0, 0), _camera_at(40, 0)])
    centre = np.zeros(3)
    assert not novel_view_direction(_camera_at(5, 5), keyframes, centre, 10.0)  # 7.1 deg away
    assert novel_view_direction(_camera_at(0, 12), keyframes, centre, 10.0)
    assert novel_view_direction(_camera_at(20, 0), keyframes, centre, 10.0)
    # near the pole azimuth means little: 60 deg of azimuth at 85 deg of elevation is 5 deg away
    polar = np.stack([_camera_at(0, 85)])
    assert not novel_view_direction(_camera_at(60, 85), polar, centre, 10.0)
    assert novel_view(_camera_at(60, 85), polar, centre, 10.0)  # the paper's rule: 60 > 10
    # a ring above a full ring: new views for the view-direction rule, none for the paper's
    ring = np.stack([_camera_at(a, 0) for a in range(-180, 180, 10)])
    assert novel_object_view(ObjectKeyframeRule.VIEW_DIRECTION, _camera_at(5, 30), ring, centre, 10)
    assert not novel_object_view(
        ObjectKeyframeRule.AZIMUTH_ELEVATION, _camera_at(5, 30), np.concatenate(
            [ring, _camera_at(0, 30)[None]]), centre, 10)


def test_object_centre_is_the_mean_of_the_fused_object_points() -> None:
    mask = np.zeros((8, 8), dtype=bool)
    mask[2:4, 2:4] = True
    first = _keyframe(0, np.eye(4), depth=2.0, mask=mask, focal=8.0)
    moved, far = np.eye(4), np.eye(4)
    moved[:3, 3] = [0.1, 0.0, 0.0]
    far[:3, 3] = [5.0, 0.0, 0.0]
    second = _keyframe(1, moved, depth=2.0, mask=mask, focal=8.0)
    elsewhere = _keyframe(2, far, depth=2.0, mask=mask, focal=8.0)
    # pixels 2, 3 at focal 8 and depth 2: x, y in {-0.375, -0.125}; the second keyframe's x is
    # 0.1 further; the third's points lie far outside keyframe 0's object (the anchor ball)
    centre = object_centre([first, second, elsewhere], step=1)
    np.testing.assert_allclose(centre, [-0.2, -0.25, 2.0], atol=1e-9)


def test_budget_capacity_from_count_and_bytes() -> None:
    assert KeyframeBudget(BudgetConfig(max_keyframes=None)).capacity(100) is None
    assert KeyframeBudget(BudgetConfig(max_keyframes=10)).capacity(100) == 10
    both = KeyframeBudget(BudgetConfig(max_keyframes=10, max_cache_bytes=450))
    assert both.capacity(100) == 4
    assert KeyframeBudget(BudgetConfig(max_keyframes=None, max_cache_bytes=50)).capacity(100) == 1


def test_oldest_eviction_drops_the_oldest_after_keyframe_zero() -> None:
    budget = KeyframeBudget(BudgetConfig(max_keyframes=4, eviction="oldest"))
    keyframes = [_keyframe(i, _camera_at(10 * i, 0)) for i in range(4)]
    assert budget.select_evictions(keyframes, 1) == (1,)
    assert budget.select_evictions(keyframes[:3], 1) == ()


def test_redundant_eviction_drops_a_keyframe_of_the_closest_pair() -> None:
    budget = KeyframeBudget(BudgetConfig(max_keyframes=4, eviction="redundant"))
    poses = [_camera_at(0, 0), _camera_at(60, 0), _camera_at(61, 0), _camera_at(120, 0)]
    keyframes = [_keyframe(i, p) for i, p in enumerate(poses)]
    assert budget.select_evictions(keyframes, 1) in {(1,), (2,)}


@settings(max_examples=60, deadline=None)
@given(
    count=st.integers(1, 12),
    max_keyframes=st.integers(2, 8),
    policy=st.sampled_from(["oldest", "redundant"]),
    seed=st.integers(0, 2**16),
)
def test_eviction_keeps_the_budget_and_never_drops_keyframe_zero(
    count: int, max_keyframes: int, policy: str, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    keyframes = [_keyframe(i, _camera_at(*rng.uniform(-80, 80, 2))) for i in range(count)]
    budget = KeyframeBudget(BudgetConfig(max_keyframes=max_keyframes, eviction=policy))
    evicted = budget.select_evictions(keyframes, 1)
    assert 0 not in evicted
    assert len(set(evicted)) == len(evicted)
    assert count - len(evicted) + 1 <= max_keyframes  # room for the new keyframe
    assert len(evicted) == max(0, count + 1 - max_keyframes)

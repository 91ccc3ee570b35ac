"""Rigid/similarity transforms, named quaternion orders and the Umeyama alignment."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from kvtracker_sdk.geometry import (
    Sim3,
    check_rigid,
    invert_rigid,
    project_to_rotation,
    quat_wxyz_from_rotation,
    quat_xyzw_from_rotation,
    rotation_angle_deg,
    rotation_from_quat_wxyz,
    rotation_from_quat_xyzw,
    umeyama_alignment,
)

seeds = st.integers(min_value=0, max_value=2**31 - 1)


def random_sim3(rng: np.random.Generator) -> Sim3:
    return Sim3(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3), float(np.exp(rng.normal())))


def random_pose(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.normal(size=3)
    return T


def test_quaternion_orders_are_explicit() -> None:
    # 90 degrees about z: xyzw = (0, 0, sin45, cos45)
    R = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    s = np.sqrt(0.5)
    np.testing.assert_allclose(quat_xyzw_from_rotation(R), [0, 0, s, s], atol=1e-12)
    np.testing.assert_allclose(quat_wxyz_from_rotation(R), [s, 0, 0, s], atol=1e-12)
    np.testing.assert_allclose(rotation_from_quat_xyzw([0, 0, s, s]), R, atol=1e-12)
    np.testing.assert_allclose(rotation_from_quat_wxyz([s, 0, 0, s]), R, atol=1e-12)


@settings(max_examples=50, deadline=None)
@given(seeds)
def test_quaternion_round_trip_and_positive_scalar(seed: int) -> None:
    R = Rotation.random(random_state=np.random.default_rng(seed)).as_matrix()
    q = quat_xyzw_from_rotation(R)
    assert q[3] >= 0
    np.testing.assert_allclose(rotation_from_quat_xyzw(q), R, atol=1e-12)
    np.testing.assert_allclose(rotation_from_quat_wxyz(quat_wxyz_from_rotation(R)), R, atol=1e-12)


@settings(max_examples=50, deadline=None)
@given(seeds)
def test_invert_rigid_and_check(seed: int) -> None:
    T = random_pose(np.random.default_rng(seed))
    assert check_rigid(T)
    np.testing.assert_allclose(invert_rigid(T) @ T, np.eye(4), atol=1e-12)
    bad = T.copy()
    bad[:3, :3] *= 1.1
    assert not check_rigid(bad)


@settings(max_examples=50, deadline=None)
@given(seeds)
def test_sim3_algebra(seed: int) -> None:
    rng = np.random.default_rng(seed)
    a, b = random_sim3(rng), random_sim3(rng)
    p = rng.normal(size=(5, 3))
    np.testing.assert_allclose((a @ b).apply_to_points(p), a.apply_to_points(b.apply_to_points(p)), atol=1e-9)
    np.testing.assert_allclose(a.inverse().apply_to_points(a.apply_to_points(p)), p, atol=1e-9)
    np.testing.assert_allclose(Sim3.from_matrix(a.matrix()).matrix(), a.matrix(), atol=1e-9)
    moved = a.apply_to_pose(random_pose(rng))
    assert check_rigid(moved, atol=1e-9)


@settings(max_examples=50, deadline=None)
@given(seeds, st.booleans())
def test_umeyama_recovers_known_transform(seed: int, with_scale: bool) -> None:
    rng = np.random.default_rng(seed)
    truth = random_sim3(rng)
    if not with_scale:
        truth = Sim3(truth.rotation, truth.translation, 1.0)
    src = rng.normal(size=(20, 3))
    est = umeyama_alignment(src, truth.apply_to_points(src), with_scale=with_scale)
    np.testing.assert_allclose(est.matrix(), truth.matrix(), atol=1e-8)


def test_umeyama_rejects_mismatched_input() -> None:
    with pytest.raises(ValueError):
        umeyama_alignment(np.zeros((3, 3)), np.zeros((4, 3)))


def test_project_to_rotation_and_angle() -> None:
    rng = np.random.default_rng(0)
    R = Rotation.random(random_state=rng).as_matrix()
    noisy = R + 1e-3 * rng.normal(size=(3, 3))
    P = project_to_rotation(noisy)
    np.testing.assert_allclose(P.T @ P, np.eye(3), atol=1e-12)
    assert np.linalg.det(P) == pytest.approx(1.0)
    assert rotation_angle_deg(R, P) < 0.5
    Rz = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    assert rotation_angle_deg(np.eye(3), Rz) == pytest.approx(30.0)

"""Image boxes and oriented 3D boxes."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kvtracker_sdk.geometry.boxes import OrientedBox, box_iou, grow_box, mask_box


def test_iou_of_overlapping_disjoint_and_equal_boxes() -> None:
    assert box_iou((0, 0, 2, 2), (1, 1, 3, 3)) == pytest.approx(1 / 7)
    assert box_iou((0, 0, 1, 1), (2, 2, 3, 3)) == 0.0
    assert box_iou((0, 0, 4, 2), (0, 0, 4, 2)) == 1.0
    assert box_iou((0, 0, 0, 0), (0, 0, 0, 0)) == 0.0


def test_grow_box_clips_to_the_image() -> None:
    assert grow_box((10, 20, 30, 40), 50, (100, 200)) == (0.0, 0.0, 80.0, 90.0)


def test_mask_box_is_exclusive_at_the_far_side() -> None:
    mask = np.zeros((6, 8), dtype=bool)
    mask[2:4, 3:7] = True
    assert mask_box(mask) == (3.0, 2.0, 7.0, 4.0)
    assert mask_box(np.zeros((3, 3), dtype=bool)) is None


def test_oriented_box_fit_recovers_a_rotated_box() -> None:
    rng = np.random.default_rng(7)
    half = np.array([2.0, 1.0, 0.25])
    local = rng.uniform(-1, 1, size=(20000, 3)) * half
    rotation = Rotation.from_euler("xyz", [20, -35, 60], degrees=True).as_matrix()
    centre = np.array([1.0, -2.0, 3.0])
    box = OrientedBox.fit(local @ rotation.T + centre, trim=0.0)
    np.testing.assert_allclose(box.half_extents, half, rtol=0.03)  # PCA axes from samples
    np.testing.assert_allclose(box.centre, centre, atol=0.02)
    # the axes up to sign: |R_fit^T R| is the identity
    np.testing.assert_allclose(np.abs(box.T_ref_box[:3, :3].T @ rotation), np.eye(3), atol=0.02)
    assert np.linalg.det(box.T_ref_box[:3, :3]) == pytest.approx(1.0)
    corners = box.corners()
    assert corners.shape == (8, 3)
    moved = box.transformed(np.diag([1.0, 1.0, 1.0, 1.0]))
    np.testing.assert_allclose(moved.corners(), corners)

"""The demo's hand-held orbit: a plausible camera path, seeded, always aimed near the object."""

from __future__ import annotations

import numpy as np
import pytest

from kvtracker_sdk.cli.demo_trajectory import default_loss_segment, handheld_orbit


def test_path_circles_the_object_unevenly_and_keeps_it_in_view() -> None:
    truth = handheld_orbit(600, seed=1)
    poses = truth.poses
    np.testing.assert_allclose(truth.timestamps[1] - truth.timestamps[0], 1 / 30)
    rotations = poses[:, :3, :3]
    identity = np.einsum("nji,njk->nik", rotations, rotations)
    np.testing.assert_allclose(identity, np.broadcast_to(np.eye(3), identity.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-9)
    centres = poses[:, :3, 3]
    radius = np.linalg.norm(centres[:, :2], axis=1)
    assert radius.min() > 0.9 and radius.max() < 1.5  # 1.2 m +- 12 cm breathing +- shake
    azimuth = np.unwrap(np.arctan2(centres[:, 1], centres[:, 0]))
    assert azimuth[-1] - azimuth[0] == pytest.approx(2 * np.pi, abs=0.1)  # one turn
    steps = np.diff(azimuth)
    assert steps.min() > 0 and steps.max() > 1.5 * steps.min()  # always forward, uneven speed
    # the optical axis (z) points within a few degrees of the object at the origin
    to_object = -centres / np.linalg.norm(centres, axis=1, keepdims=True)
    off_axis = np.degrees(np.arccos(np.clip(np.sum(poses[:, :3, 2] * to_object, axis=1), -1, 1)))
    assert off_axis.max() < 8.0 and off_axis.mean() > 0.5  # near, never exactly, on the object
    # hand shake: frame-to-frame jitter is present but small (a few mm at 30 Hz)
    jerk = np.linalg.norm(np.diff(centres, n=2, axis=0), axis=1)
    assert 1e-4 < np.median(jerk) < 5e-3


def test_seed_decides_the_path() -> None:
    a, b, c = handheld_orbit(90, seed=0), handheld_orbit(90, seed=0), handheld_orbit(90, seed=1)
    np.testing.assert_array_equal(a.poses, b.poses)
    assert np.abs(a.poses - c.poses).max() > 1e-3


def test_loss_segment_is_one_and_a_half_seconds_after_the_middle() -> None:
    assert default_loss_segment(600) == (330, 375)
    assert default_loss_segment(150) == (82, 127)
    assert default_loss_segment(100) is None  # too short to lose and recover

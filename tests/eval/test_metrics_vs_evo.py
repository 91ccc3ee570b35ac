"""Our ATE / RPE equal evo's on the real TUM fr2_desk ground truth, perturbed (tolerance 1e-6).

The estimate: every 7th ground-truth pose, its stamp jittered by up to 4 ms, its position and
orientation perturbed by seeded noise (2 cm per axis, 1 degree per axis), then moved by a known
similarity (scale 0.4, a 75-degree rotation, a 2 m translation) — what a monocular tracker's
output looks like. evo (GPL-3) is a development dependency, imported here only.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kvtracker_sdk.eval.association import associate_trajectories
from kvtracker_sdk.eval.metrics import ErrorStats
from kvtracker_sdk.eval.report import evaluate_trajectories
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.io.files.trajectory import Trajectory, read_tum
from tests.helpers import dev_dependency, shared_path

TOL = 1e-6  # the bar; the two implementations actually agree to ~1e-12
KNOWN = Sim3(Rotation.from_rotvec([0.3, -1.2, 0.5]).as_matrix(), [2.0, -1.0, 0.5], 0.4)
STATS = ("rmse", "mean", "median", "std", "min", "max")


@pytest.fixture(scope="module")
def ground_truth() -> Trajectory:
    return read_tum(shared_path("data", "tum_fr2_desk", "groundtruth.txt"))


@pytest.fixture(scope="module")
def estimate(ground_truth: Trajectory) -> Trajectory:
    rng = np.random.default_rng(2026)
    idx = np.arange(0, len(ground_truth), 7)
    poses = ground_truth.poses[idx].copy()
    poses[:, :3, 3] += rng.normal(0.0, 0.02, size=(len(idx), 3))
    noise = Rotation.from_rotvec(rng.normal(0.0, np.radians(1.0), size=(len(idx), 3)))
    poses[:, :3, :3] = noise.as_matrix() @ poses[:, :3, :3]
    stamps = ground_truth.stamps[idx] + rng.uniform(-0.004, 0.004, size=len(idx))
    return Trajectory(stamps, KNOWN.apply_to_pose(poses))


def _evo_pair(est: Trajectory, ref: Trajectory) -> tuple[Any, Any]:
    """evo's (reference, estimate) after its own association, max_diff 10 ms."""
    evo_trajectory = dev_dependency("evo.core.trajectory")
    evo_sync = dev_dependency("evo.core.sync")
    ref_evo = evo_trajectory.PoseTrajectory3D(poses_se3=list(ref.poses), timestamps=ref.stamps)
    est_evo = evo_trajectory.PoseTrajectory3D(poses_se3=list(est.poses), timestamps=est.stamps)
    return evo_sync.associate_trajectories(ref_evo, est_evo, max_diff=0.01)


def _evo_stats(metric_cls: Any, relation: str, data: Any, **kwargs: Any) -> dict[str, float]:
    metrics = dev_dependency("evo.core.metrics")
    metric = metric_cls(getattr(metrics.PoseRelation, relation), **kwargs)
    metric.process_data(data)
    return {k: float(v) for k, v in metric.get_all_statistics().items()}


def _assert_stats_equal(ours: ErrorStats, evo: dict[str, float]) -> None:
    for name in STATS:
        assert getattr(ours, name) == pytest.approx(evo[name], abs=TOL), name


def test_association_matches_evo(ground_truth: Trajectory, estimate: Trajectory) -> None:
    ref_evo, est_evo = _evo_pair(estimate, ground_truth)
    ours = associate_trajectories(estimate, ground_truth, max_diff=0.01)
    assert len(ours) == est_evo.num_poses == len(estimate)  # every jittered stamp finds a match
    np.testing.assert_array_equal(ours.est.stamps, est_evo.timestamps)
    np.testing.assert_array_equal(ours.ref.stamps, ref_evo.timestamps)
    assert ours.max_gap <= 0.004 + 0.0035 / 2 + 1e-9  # jitter plus half the 300 Hz spacing


@pytest.mark.parametrize("alignment", ["sim3", "se3"])
def test_ate_and_rpe_equal_evo(
    ground_truth: Trajectory, estimate: Trajectory, alignment: str
) -> None:
    metrics = dev_dependency("evo.core.metrics")
    units = dev_dependency("evo.core.units")
    ref_evo, est_evo = _evo_pair(estimate, ground_truth)
    est_evo = copy.deepcopy(est_evo)
    rotation, translation, scale = est_evo.align(ref_evo, correct_scale=alignment == "sim3")
    data = (ref_evo, est_evo)

    report = evaluate_trajectories(estimate, ground_truth, alignment=alignment)
    assert report.ate.transform.scale == pytest.approx(scale, abs=TOL)
    np.testing.assert_allclose(report.ate.transform.rotation, rotation, atol=TOL)
    np.testing.assert_allclose(report.ate.transform.translation, translation, atol=TOL)
    _assert_stats_equal(report.ate.translation, _evo_stats(metrics.APE, "translation_part", data))
    _assert_stats_equal(
        report.ate.rotation_deg, _evo_stats(metrics.APE, "rotation_angle_deg", data)
    )

    for delta, all_pairs in ((1, False), (10, True), (25, False)):
        ours = evaluate_trajectories(
            estimate, ground_truth, alignment=alignment, delta=delta, all_pairs=all_pairs
        ).rpe
        rpe_kwargs = {"delta": delta, "delta_unit": units.Unit.frames, "all_pairs": all_pairs}
        evo_t = _evo_stats(metrics.RPE, "translation_part", data, **rpe_kwargs)
        evo_r = _evo_stats(metrics.RPE, "rotation_angle_deg", data, **rpe_kwargs)
        _assert_stats_equal(ours.translation, evo_t)
        _assert_stats_equal(ours.rotation_deg, evo_r)


def test_sim3_alignment_recovers_the_known_similarity(
    ground_truth: Trajectory, estimate: Trajectory
) -> None:
    """Independent of evo: the fitted transform undoes KNOWN, and the ATE is the noise level."""
    report = evaluate_trajectories(estimate, ground_truth, alignment="sim3")
    undo = KNOWN.inverse()
    assert report.ate.transform.scale == pytest.approx(undo.scale, rel=2e-3)
    angle = Rotation.from_matrix(report.ate.transform.rotation @ undo.rotation.T).magnitude()
    assert np.degrees(angle) < 0.1
    # 2 cm per axis -> 2 * sqrt(3) = 3.46 cm RMS position error (association adds < 1 mm)
    assert report.ate.translation.rmse == pytest.approx(0.02 * np.sqrt(3), rel=0.05)
    assert report.ate.rotation_deg.rmse == pytest.approx(np.sqrt(3), rel=0.05)

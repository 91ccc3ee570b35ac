"""ATE, RPE and cm-degree recall on synthetic trajectories with known answers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kvtracker_sdk.errors import ConfigError, EvaluationError, TrajectoryError
from kvtracker_sdk.eval.metrics import (
    Alignment,
    ErrorStats,
    absolute_trajectory_error,
    align_poses,
    cm_degree_recall,
    relative_pose_error,
)
from kvtracker_sdk.geometry.sim3 import Sim3


def _orbit(n: int = 40, seed: int = 0) -> np.ndarray:
    """A camera circling a point at 2 m, looking inwards, with some height change: [n, 4, 4]."""
    rng = np.random.default_rng(seed)
    angles = np.linspace(0, 1.5 * np.pi, n)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = 2 * np.cos(angles)
    poses[:, 1, 3] = 0.3 * np.sin(3 * angles) + rng.normal(0, 0.01, n)
    poses[:, 2, 3] = 2 * np.sin(angles)
    poses[:, :3, :3] = Rotation.from_euler("y", (-angles - np.pi / 2)[:, None]).as_matrix()
    return poses


def _right_rotate(poses: np.ndarray, degrees: float) -> np.ndarray:
    """Each camera turned by ``degrees`` about its own z axis (centres unchanged)."""
    out = poses.copy()
    out[:, :3, :3] = poses[:, :3, :3] @ Rotation.from_euler("z", degrees, degrees=True).as_matrix()
    return out


def test_error_stats_match_hand_computed_values() -> None:
    stats = ErrorStats.from_errors(np.array([3.0, 4.0, 0.0, 1.0]))
    assert stats.rmse == pytest.approx(np.sqrt(26 / 4))
    assert (stats.mean, stats.median, stats.min, stats.max, stats.count) == (2.0, 2.0, 0.0, 4.0, 4)
    assert stats.std == pytest.approx(np.sqrt(2.5))  # population std, like evo
    assert stats.to_dict()["count"] == 4


def test_sim3_alignment_undoes_a_similarity_exactly() -> None:
    ref = _orbit()
    similarity = Sim3(Rotation.from_rotvec([0.4, 1.0, -0.2]).as_matrix(), [1.0, -3.0, 0.2], 2.5)
    est = similarity.apply_to_pose(ref)
    ate = absolute_trajectory_error(est, ref, alignment="sim3")
    assert ate.translation.max < 1e-9 and ate.rotation_deg.max < 1e-6
    assert ate.transform.scale == pytest.approx(1 / 2.5, rel=1e-12)
    aligned, _ = align_poses(est, ref, Alignment.SIM3)
    np.testing.assert_allclose(aligned, ref, atol=1e-9)
    # SE(3) cannot undo the scale: the error stays large; NONE leaves the estimate as is
    assert absolute_trajectory_error(est, ref, alignment=Alignment.SE3).translation.rmse > 1.0
    none = absolute_trajectory_error(est, ref, alignment="none")
    assert none.transform.scale == 1.0 and none.translation.rmse > 1.0
    assert relative_pose_error(est, ref, alignment="sim3").translation.max < 1e-9


def test_constant_offsets_give_known_ate_and_zero_rpe() -> None:
    ref = _orbit()
    shifted = ref.copy()
    shifted[:, :3, 3] += [0.03, 0.0, 0.04]  # 5 cm, the same for every pose
    ate = absolute_trajectory_error(shifted, ref, alignment="none")
    np.testing.assert_allclose(ate.translation_errors, 0.05, atol=1e-12)
    assert ate.rotation_deg.max < 1e-6
    rpe = relative_pose_error(shifted, ref, alignment="none")
    assert rpe.translation.max < 1e-12  # a world-frame shift keeps every relative motion

    turned = _right_rotate(ref, 2.0)
    ate = absolute_trajectory_error(turned, ref, alignment="none")
    np.testing.assert_allclose(ate.rotation_errors_deg, 2.0, atol=1e-9)
    assert ate.translation.max < 1e-12


def test_rpe_sees_a_single_jump_once_per_pair_that_spans_it() -> None:
    ref = _orbit(n=21)
    est = ref.copy()
    est[10:, :3, 3] += [0.0, 0.1, 0.0]  # a 10 cm jump between frames 9 and 10
    rpe = relative_pose_error(est, ref, delta=1, alignment="none")
    assert rpe.pairs.shape == (20, 2) and rpe.translation.count == 20
    assert rpe.translation.max == pytest.approx(0.1, abs=1e-9)
    assert np.count_nonzero(_pair_errors(est, ref, rpe.pairs) > 1e-9) == 1
    # consecutive pairs (evo's default) step by delta; all_pairs slides by one
    assert relative_pose_error(est, ref, delta=5, alignment="none").pairs.tolist() == [
        [0, 5],
        [5, 10],
        [10, 15],
        [15, 20],
    ]
    all_pairs = relative_pose_error(est, ref, delta=5, all_pairs=True, alignment="none")
    assert len(all_pairs.pairs) == 16
    assert np.count_nonzero(_pair_errors(est, ref, all_pairs.pairs) > 1e-9) == 5  # i = 5..9


def _pair_errors(est: np.ndarray, ref: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Translation RPE per pair, computed the slow way with general matrix inverses."""
    out = []
    for i, j in pairs:
        error = np.linalg.inv(np.linalg.inv(ref[i]) @ ref[j]) @ (np.linalg.inv(est[i]) @ est[j])
        out.append(np.linalg.norm(error[:3, 3]))
    return np.array(out)


def test_cm_degree_recall_counts_poses_within_both_thresholds() -> None:
    ref = _orbit(n=5)
    est = ref.copy()
    # translation errors 0.5, 2, 4, 6, 0.5 cm; the last pose is also turned by 2 degrees
    est[:, :3, 3] += np.array(
        [[0.005, 0, 0], [0.02, 0, 0], [0, 0.04, 0], [0, 0, 0.06], [0.005, 0, 0]]
    )
    est[4] = _right_rotate(est[4:5], 2.0)[0]
    result = cm_degree_recall(est, ref, alignment="none")
    assert result.thresholds == (1.0, 3.0, 5.0)
    assert result.recall == pytest.approx((0.2, 0.6, 0.8))
    assert result.to_dict()["recall"] == {"1cm_1deg": 0.2, "3cm_3deg": 0.6, "5cm_5deg": 0.8}
    # the same trajectories in millimetres give the same recall with metres_per_unit = 0.001
    est_mm, ref_mm = est.copy(), ref.copy()
    est_mm[:, :3, 3] *= 1000.0
    ref_mm[:, :3, 3] *= 1000.0
    mm = cm_degree_recall(est_mm, ref_mm, thresholds=[2.5], alignment="none", metres_per_unit=1e-3)
    assert mm.recall == (0.6,)  # 0.5 cm, 2 cm, and 0.5 cm with 2 degrees are within 2.5


def test_bad_inputs_are_typed_errors() -> None:
    ref = _orbit(n=6)
    with pytest.raises(EvaluationError, match="match them by time first"):
        absolute_trajectory_error(ref[:5], ref)
    with pytest.raises(EvaluationError, match="at least 3"):
        absolute_trajectory_error(ref[:2], ref[:2])
    with pytest.raises(TrajectoryError, match=r"\[N, 4, 4\]"):
        absolute_trajectory_error(ref[:, :3], ref[:, :3])
    bad = ref.copy()
    bad[0, 0, 3] = np.nan
    with pytest.raises(TrajectoryError, match="NaN"):
        absolute_trajectory_error(bad, ref)
    with pytest.raises(ConfigError, match="unknown alignment"):
        absolute_trajectory_error(ref, ref, alignment="affine")
    with pytest.raises(ConfigError, match="delta"):
        relative_pose_error(ref, ref, delta=0)
    with pytest.raises(ConfigError, match="delta"):
        relative_pose_error(ref, ref, delta=1.5)  # type: ignore[arg-type]
    with pytest.raises(EvaluationError, match="no pose pair"):
        relative_pose_error(ref, ref, delta=6)
    with pytest.raises(ConfigError, match="thresholds"):
        cm_degree_recall(ref, ref, thresholds=[0.0])
    assert absolute_trajectory_error(ref[:1], ref[:1], alignment="none").translation.count == 1

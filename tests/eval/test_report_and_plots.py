"""The one-call evaluation report and the trajectory plot PNG."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kvtracker_sdk.errors import EvaluationError, MissingDependencyError, TrajectoryError
from kvtracker_sdk.eval.plots import break_at_gaps, plot_trajectory
from kvtracker_sdk.eval.report import evaluate_trajectories
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.io.files.trajectory import Trajectory


@pytest.fixture
def pair() -> tuple[Trajectory, Trajectory]:
    """A 300 Hz reference helix and a 30 Hz, scaled, rotated, noisy estimate of it."""
    rng = np.random.default_rng(5)
    t_ref = np.arange(0, 10, 1 / 300)
    ref_poses = np.tile(np.eye(4), (len(t_ref), 1, 1))
    ref_poses[:, :3, 3] = np.stack([np.cos(t_ref), np.sin(t_ref), 0.1 * t_ref], axis=1)
    ref_poses[:, :3, :3] = Rotation.from_rotvec(np.outer(t_ref, [0, 0, 0.3])).as_matrix()
    idx = np.arange(0, len(t_ref), 10)
    est_poses = ref_poses[idx].copy()
    est_poses[:, :3, 3] += rng.normal(0, 0.005, (len(idx), 3))
    similarity = Sim3(Rotation.from_rotvec([0.2, 0.1, 2.0]).as_matrix(), [5.0, 0.0, 1.0], 3.0)
    estimate = Trajectory(t_ref[idx] + 0.001, similarity.apply_to_pose(est_poses))
    return estimate, Trajectory(t_ref, ref_poses)


def test_report_bundles_every_metric_and_serialises(pair: tuple[Trajectory, Trajectory]) -> None:
    estimate, reference = pair
    report = evaluate_trajectories(estimate, reference, delta=3, all_pairs=True)
    assert len(report.association) == len(estimate) == 300
    assert report.ate.transform.scale == pytest.approx(1 / 3.0, rel=1e-2)
    # 5 mm per axis -> 8.7 mm RMS after alignment
    assert report.ate.translation.rmse == pytest.approx(0.005 * np.sqrt(3), rel=0.1)
    assert report.rpe.delta == 3 and report.rpe.all_pairs
    assert report.cm_degree.recall[-1] == 1.0  # every pose within 5 cm / 5 degrees
    np.testing.assert_allclose(
        report.aligned_estimate.positions, report.association.ref.positions, atol=0.03
    )
    data = json.loads(json.dumps(report.to_dict()))
    assert set(data) == {"association", "ate", "rpe", "cm_degree"}
    assert data["ate"]["alignment"]["method"] == "sim3"
    assert data["ate"]["translation"]["rmse"] == report.ate.translation.rmse
    summary = report.summary()
    assert "matched 300 of 300" in summary and "ATE  RMSE 0.0" in summary


def test_report_fails_loudly_when_clocks_disagree(pair: tuple[Trajectory, Trajectory]) -> None:
    estimate, reference = pair
    with pytest.raises(EvaluationError, match="no timestamps match"):
        evaluate_trajectories(estimate, reference, offset=100.0)
    assert (
        len(evaluate_trajectories(estimate, reference, offset=0.002, max_diff=0.0015).association)
        == 300
    )


def test_plot_writes_a_png_with_and_without_reference(
    tmp_path: Path, pair: tuple[Trajectory, Trajectory]
) -> None:
    estimate, reference = pair
    report = evaluate_trajectories(estimate, reference)
    path = plot_trajectory(
        tmp_path / "eval.png",
        report.aligned_estimate,
        report.association.ref,
        translation_errors=report.ate.translation_errors,
        title="helix",
    )
    image = cv2.imread(str(path))
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert image.shape == (462, 1848, 3)  # 4 panels of 4.2 x 4.2 inches at 110 dpi
    assert image.std() > 10  # something was drawn
    alone = cv2.imread(str(plot_trajectory(tmp_path / "track.png", estimate)))
    assert alone.shape == (462, 1386, 3)  # 3 projections, no error panel
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eval.png", "track.png"]


def test_plot_errors(
    tmp_path: Path, pair: tuple[Trajectory, Trajectory], monkeypatch: pytest.MonkeyPatch
) -> None:
    estimate, _ = pair
    with pytest.raises(TrajectoryError, match="empty"):
        plot_trajectory(tmp_path / "x.png", Trajectory([], []))
    with pytest.raises(TrajectoryError, match="3 errors for 300"):
        plot_trajectory(tmp_path / "x.png", estimate, translation_errors=np.zeros(3))
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)  # as if matplotlib were absent
    with pytest.raises(MissingDependencyError, match=r"pip install -e \"\.\[viz\]\""):
        plot_trajectory(tmp_path / "x.png", estimate)
    assert list(tmp_path.iterdir()) == []


def test_importing_the_eval_modules_loads_neither_matplotlib_nor_evo() -> None:
    code = (
        "import sys, kvtracker_sdk.eval.report, kvtracker_sdk.eval.plots; "
        "print([m for m in ('matplotlib', 'evo', 'cv2') if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_lines_break_where_the_tracker_was_lost() -> None:
    stamps = np.array([0.0, 0.1, 0.2, 0.3, 1.5, 1.6, 1.7, 3.0])  # two gaps (frames missing)
    positions = np.arange(24, dtype=float).reshape(8, 3)
    times, line = break_at_gaps(stamps, positions)
    assert len(times) == len(line) == 10
    gaps = np.flatnonzero(np.isnan(times))
    assert gaps.tolist() == [4, 8] and np.isnan(line[gaps]).all()
    np.testing.assert_array_equal(line[~np.isnan(times)], positions)
    steady = np.arange(5) * 0.1  # no gap: unchanged
    np.testing.assert_array_equal(break_at_gaps(steady, steady)[1], steady)

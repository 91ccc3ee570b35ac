"""One call from two trajectories to every number: association, ATE, RPE, cm-degree recall.

This is what ``kvtracker eval EST GT`` runs; an app or a benchmark script can call it directly:

    from kvtracker_sdk.eval.report import evaluate_trajectories
    from kvtracker_sdk.io.files.trajectory import read_trajectory

    report = evaluate_trajectories(read_trajectory("est.txt"), read_trajectory("gt.txt"))
    print(report.summary())
    json.dump(report.to_dict(), open("eval.json", "w"))
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from kvtracker_sdk.eval.association import Association, associate_trajectories
from kvtracker_sdk.eval.metrics import (
    Alignment,
    ATEResult,
    CmDegreeResult,
    RPEResult,
    absolute_trajectory_error,
    cm_degree_recall,
    relative_pose_error,
)
from kvtracker_sdk.io.files.trajectory import Trajectory

__all__ = ["EvaluationReport", "evaluate_trajectories"]


@dataclass(frozen=True)
class EvaluationReport:
    """Every metric of one estimate against one reference.

    ``aligned_estimate`` is the matched estimate moved onto the reference by the ATE alignment
    (for plots next to ``association.ref``).
    """

    association: Association
    ate: ATEResult
    rpe: RPEResult
    cm_degree: CmDegreeResult
    aligned_estimate: Trajectory

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the association summary and each metric's ``to_dict()``."""
        return {
            "association": self.association.to_dict(),
            "ate": self.ate.to_dict(),
            "rpe": self.rpe.to_dict(),
            "cm_degree": self.cm_degree.to_dict(),
        }

    def summary(self) -> str:
        """A few human-readable lines (the reference's units are assumed to be metres)."""
        a, ate, rpe = self.association, self.ate, self.rpe
        recall = ", ".join(
            f"{k:g}cm/{k:g}deg {r:.1%}"
            for k, r in zip(self.cm_degree.thresholds, self.cm_degree.recall, strict=True)
        )
        pairs = "all pairs" if rpe.all_pairs else "consecutive pairs"
        return "\n".join(
            [
                f"matched {len(a)} of {a.est_total} estimated poses to {a.ref_total} reference "
                f"poses (max gap {a.max_gap * 1e3:.2f} ms)",
                f"alignment {ate.alignment.value}: scale {ate.transform.scale:.6g}",
                f"ATE  RMSE {ate.translation.rmse:.4f} m  mean {ate.translation.mean:.4f}  "
                f"median {ate.translation.median:.4f}  max {ate.translation.max:.4f}  "
                f"| rotation RMSE {ate.rotation_deg.rmse:.3f} deg",
                f"RPE  (delta {rpe.delta} frames, {pairs}) translation RMSE "
                f"{rpe.translation.rmse:.4f} m  rotation RMSE {rpe.rotation_deg.rmse:.3f} deg",
                f"cm-degree recall: {recall}",
            ]
        )


def evaluate_trajectories(
    est: Trajectory,
    ref: Trajectory,
    *,
    max_diff: float = 0.01,
    offset: float = 0.0,
    alignment: Alignment | str = Alignment.SIM3,
    delta: int = 1,
    all_pairs: bool = False,
    cm_degree_thresholds: Sequence[float] = (1.0, 3.0, 5.0),
) -> EvaluationReport:
    """Associate ``est`` with ``ref`` by timestamp, then compute ATE, RPE and cm-degree recall.

    ``max_diff`` / ``offset`` (seconds) go to
    :func:`~kvtracker_sdk.eval.association.associate_trajectories`; ``alignment`` is used by
    every metric; ``delta`` / ``all_pairs`` select the RPE pairs. Raises
    :class:`~kvtracker_sdk.errors.EvaluationError` when too few poses match.
    """
    association = associate_trajectories(est, ref, max_diff=max_diff, offset=offset)
    est_poses, ref_poses = association.est.poses, association.ref.poses
    ate = absolute_trajectory_error(est_poses, ref_poses, alignment=alignment)
    rpe = relative_pose_error(
        est_poses, ref_poses, delta=delta, all_pairs=all_pairs, alignment=alignment
    )
    cm_degree = cm_degree_recall(
        est_poses, ref_poses, thresholds=cm_degree_thresholds, alignment=alignment
    )
    aligned = Trajectory(association.est.stamps, ate.transform.apply_to_pose(est_poses))
    return EvaluationReport(association, ate, rpe, cm_degree, aligned)

"""Timestamp association: pair each pose of one trajectory with the nearest pose of another.

An estimate and a ground truth are sampled at different times (a tracker's frames, a motion
capture system at 100-300 Hz). Before comparing them each pose of the *shorter* trajectory is
paired with the nearest-in-time pose of the longer one, if that pose is within ``max_diff``
seconds; poses without such a partner are dropped.

The rule is the one evo's ``associate_trajectories`` (nearest time) applies, so our numbers and
evo's are computed on the same pairs: search from the shorter trajectory, ties go to the earlier
stamp, and a pose of the longer trajectory may be used twice when the shorter one is sampled
faster than it (TUM's ``associate.py`` differs here: it pairs greedily one-to-one).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from kvtracker_sdk.errors import ConfigError, EvaluationError
from kvtracker_sdk.io.files.trajectory import Trajectory

__all__ = ["Association", "associate", "associate_trajectories"]


def associate(
    query_stamps: np.ndarray,
    target_stamps: np.ndarray,
    *,
    max_diff: float = 0.01,
    target_offset: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(query_idx, target_idx)`` of nearest-stamp pairs within ``max_diff`` seconds.

    For each query stamp (in query order) the nearest of ``target_stamps + target_offset`` is
    taken if it is at most ``max_diff`` away; ties go to the earlier target stamp. The target
    stamps need not be sorted. Returns two int arrays of equal length (possibly 0).
    """
    if not np.isfinite(max_diff) or max_diff < 0:
        raise ConfigError(f"max_diff must be a finite number >= 0 seconds, got {max_diff}")
    query = np.asarray(query_stamps, dtype=np.float64).reshape(-1)
    target = np.asarray(target_stamps, dtype=np.float64).reshape(-1) + target_offset
    if len(query) == 0 or len(target) == 0:
        empty = np.zeros(0, dtype=np.intp)
        return empty, empty.copy()
    order = np.argsort(target, kind="stable")
    sorted_target = target[order]
    # Candidates: the last target stamp <= query (lower) and the first one > query (upper).
    upper = np.searchsorted(sorted_target, query, side="right")
    lower = np.clip(upper - 1, 0, len(sorted_target) - 1)
    upper = np.clip(upper, 0, len(sorted_target) - 1)
    gap_lower = np.abs(query - sorted_target[lower])
    gap_upper = np.abs(sorted_target[upper] - query)
    take_upper = gap_upper < gap_lower
    best = np.where(take_upper, upper, lower)
    gap = np.where(take_upper, gap_upper, gap_lower)
    keep = gap <= max_diff
    return np.flatnonzero(keep), order[best[keep]]


@dataclass(frozen=True)
class Association:
    """An estimate and a reference trajectory reduced to their time-matched poses.

    ``est`` and ``ref`` have the same length; pose ``i`` of one was matched with pose ``i`` of
    the other. ``est_indices`` / ``ref_indices`` index the original trajectories; ``est_total``
    / ``ref_total`` are their original lengths.
    """

    est: Trajectory
    ref: Trajectory
    est_indices: np.ndarray
    ref_indices: np.ndarray
    est_total: int
    ref_total: int
    max_diff: float
    offset: float

    def __len__(self) -> int:
        return len(self.est)

    @property
    def max_gap(self) -> float:
        """Largest time difference (seconds, after the offset) between two matched stamps."""
        return float(np.max(np.abs(self.est.stamps + self.offset - self.ref.stamps)))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no per-pose data)."""
        return {
            "matched": len(self),
            "est_poses": self.est_total,
            "ref_poses": self.ref_total,
            "max_diff_s": self.max_diff,
            "offset_s": self.offset,
            "max_gap_s": self.max_gap,
        }


def associate_trajectories(
    est: Trajectory, ref: Trajectory, *, max_diff: float = 0.01, offset: float = 0.0
) -> Association:
    """Match an estimate to a reference trajectory by timestamp (evo's nearest-time rule).

    ``offset`` (seconds) is added to the estimate's stamps before matching (``est + offset``
    is on the reference's clock). Raises :class:`~kvtracker_sdk.errors.EvaluationError` when
    no pair is within ``max_diff``.
    """
    # Query with the shorter trajectory (the estimate on a tie), as evo does, so that none of
    # its poses is lost to a neighbour's better match.
    if len(est) > len(ref):
        ref_idx, est_idx = associate(
            ref.stamps, est.stamps, max_diff=max_diff, target_offset=offset
        )
    else:
        est_idx, ref_idx = associate(
            est.stamps, ref.stamps, max_diff=max_diff, target_offset=-offset
        )
    if len(est_idx) == 0:
        raise EvaluationError(
            f"no timestamps match within {max_diff} s (offset {offset} s): estimate spans "
            f"{_span(est)}, reference spans {_span(ref)}; check the clocks or raise max_diff"
        )
    return Association(
        est=est.select(est_idx),
        ref=ref.select(ref_idx),
        est_indices=est_idx,
        ref_indices=ref_idx,
        est_total=len(est),
        ref_total=len(ref),
        max_diff=float(max_diff),
        offset=float(offset),
    )


def _span(trajectory: Trajectory) -> str:
    if len(trajectory) == 0:
        return "nothing (empty)"
    return f"{trajectory.stamps.min():.6f}-{trajectory.stamps.max():.6f} s"

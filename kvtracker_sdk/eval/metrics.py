"""Trajectory accuracy: ATE, RPE and cm-degree recall, computed as evo computes them.

All functions take time-matched pose stacks (see :mod:`kvtracker_sdk.eval.association`):
``est_poses`` and ``ref_poses``, both [N, 4, 4] float64 ``T_world_cam`` where pose ``i`` of one
was taken at the time of pose ``i`` of the other. Units: translations in the reference's unit
(metres for TUM, 7-Scenes and KITTI ground truth), rotations in degrees.

- **Alignment.** A monocular estimate lives in its own world frame and scale. ``Alignment.SIM3``
  moves it onto the reference with the least-squares similarity of the camera centres
  (Umeyama), ``SE3`` with the rigid motion only, ``NONE`` compares as is. Every metric aligns
  the estimate first and reports the transform it used.
- **ATE** (absolute trajectory error): per pose, ``|t_est - t_ref|`` after alignment, and the
  rotation angle of ``R_est^T R_ref`` (evo's APE "translation part" / "rotation angle").
- **RPE** (relative pose error) over ``delta`` frames (Sturm et al., IROS 2012):
  ``E_ij = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` with ``Q`` the reference and ``P`` the aligned estimate;
  pairs ``(i, i+delta)`` for every ``i`` (``all_pairs``) or for ``i = 0, delta, 2 delta, ...``
  (evo's default).
- **cm-degree recall**: the fraction of poses whose aligned translation error is below ``k`` cm
  *and* rotation error below ``k`` degrees, for each ``k`` (1, 3, 5 by default) — the usual
  object-pose tracking score.

evo is GPL-3 and only a development dependency: nothing here imports it, and
``tests/eval/test_metrics_vs_evo.py`` checks that the numbers agree with evo's to 1e-6.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from kvtracker_sdk.errors import ConfigError, EvaluationError, TrajectoryError
from kvtracker_sdk.geometry.se3 import invert_rigid
from kvtracker_sdk.geometry.sim3 import Sim3, umeyama_alignment

__all__ = [
    "ATEResult",
    "Alignment",
    "CmDegreeResult",
    "ErrorStats",
    "RPEResult",
    "absolute_trajectory_error",
    "align_poses",
    "cm_degree_recall",
    "relative_pose_error",
]


class Alignment(str, enum.Enum):
    """How the estimate is moved onto the reference before it is scored."""

    SIM3 = "sim3"  # rotation, translation and scale (monocular estimates)
    SE3 = "se3"  # rotation and translation (metric estimates)
    NONE = "none"  # compare in the estimate's own frame


@dataclass(frozen=True)
class ErrorStats:
    """Summary of a list of non-negative errors (evo's statistics; ``std`` is the population std)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    count: int

    @classmethod
    def from_errors(cls, errors: np.ndarray) -> ErrorStats:
        e = np.asarray(errors, dtype=np.float64)
        return cls(
            rmse=float(np.sqrt(np.mean(e**2))),
            mean=float(np.mean(e)),
            median=float(np.median(e)),
            std=float(np.std(e)),
            min=float(np.min(e)),
            max=float(np.max(e)),
            count=len(e),
        )

    def to_dict(self) -> dict[str, float | int]:
        return {name: getattr(self, name) for name in self.__dataclass_fields__}


@dataclass(frozen=True)
class ATEResult:
    """Absolute trajectory error. ``transform`` maps the estimate onto the reference.

    ``translation_errors`` [N] (reference units) and ``rotation_errors_deg`` [N] are per pose.
    """

    alignment: Alignment
    transform: Sim3
    translation: ErrorStats
    rotation_deg: ErrorStats
    translation_errors: np.ndarray
    rotation_errors_deg: np.ndarray

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (statistics and the alignment; no per-pose arrays)."""
        return {
            "alignment": _alignment_dict(self.alignment, self.transform),
            "translation": self.translation.to_dict(),
            "rotation_deg": self.rotation_deg.to_dict(),
        }


@dataclass(frozen=True)
class RPEResult:
    """Relative pose error over ``delta`` frames; ``pairs`` [P, 2] are the index pairs used."""

    delta: int
    all_pairs: bool
    alignment: Alignment
    transform: Sim3
    translation: ErrorStats
    rotation_deg: ErrorStats
    pairs: np.ndarray

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (statistics and settings; no per-pair arrays)."""
        return {
            "delta_frames": self.delta,
            "all_pairs": self.all_pairs,
            "alignment": _alignment_dict(self.alignment, self.transform),
            "translation": self.translation.to_dict(),
            "rotation_deg": self.rotation_deg.to_dict(),
        }


@dataclass(frozen=True)
class CmDegreeResult:
    """Fraction of poses within ``k`` cm and ``k`` degrees, for each ``k`` in ``thresholds``."""

    thresholds: tuple[float, ...]
    recall: tuple[float, ...]
    alignment: Alignment
    transform: Sim3
    count: int

    def to_dict(self) -> dict[str, Any]:
        """``{"recall": {"1cm_1deg": 0.42, ...}, ...}``."""
        return {
            "recall": {
                f"{k:g}cm_{k:g}deg": r for k, r in zip(self.thresholds, self.recall, strict=True)
            },
            "poses": self.count,
            "alignment": _alignment_dict(self.alignment, self.transform),
        }


def align_poses(
    est_poses: np.ndarray, ref_poses: np.ndarray, alignment: Alignment | str = Alignment.SIM3
) -> tuple[np.ndarray, Sim3]:
    """The estimate moved onto the reference, and the transform used.

    The transform is fitted to the camera centres (Umeyama; at least 3 poses for SIM3/SE3) and
    applied to whole poses, so the aligned poses are still rigid ``T_world_cam`` [N, 4, 4].
    """
    est, ref = _checked_pair(est_poses, ref_poses)
    mode = _alignment(alignment)
    if mode is Alignment.NONE:
        return est.copy(), Sim3.identity()
    if len(est) < 3:
        raise EvaluationError(
            f"{mode.value} alignment needs at least 3 matched poses, got {len(est)}"
        )
    transform = umeyama_alignment(est[:, :3, 3], ref[:, :3, 3], with_scale=mode is Alignment.SIM3)
    return transform.apply_to_pose(est), transform


def absolute_trajectory_error(
    est_poses: np.ndarray, ref_poses: np.ndarray, *, alignment: Alignment | str = Alignment.SIM3
) -> ATEResult:
    """ATE of time-matched poses [N, 4, 4] after ``alignment`` (see the module docstring)."""
    aligned, transform = align_poses(est_poses, ref_poses, alignment)
    ref = np.asarray(ref_poses, dtype=np.float64)
    t_err = np.linalg.norm(aligned[:, :3, 3] - ref[:, :3, 3], axis=1)
    r_err = _rotation_angles_deg(np.swapaxes(aligned[:, :3, :3], 1, 2) @ ref[:, :3, :3])
    return ATEResult(
        alignment=_alignment(alignment),
        transform=transform,
        translation=ErrorStats.from_errors(t_err),
        rotation_deg=ErrorStats.from_errors(r_err),
        translation_errors=t_err,
        rotation_errors_deg=r_err,
    )


def relative_pose_error(
    est_poses: np.ndarray,
    ref_poses: np.ndarray,
    *,
    delta: int = 1,
    all_pairs: bool = False,
    alignment: Alignment | str = Alignment.SIM3,
) -> RPEResult:
    """RPE over ``delta`` frames of time-matched poses [N, 4, 4] (see the module docstring).

    Rigid alignment does not change the RPE; ``SIM3`` matters because it fixes the scale.
    """
    if isinstance(delta, bool) or int(delta) != delta or delta < 1:
        raise ConfigError(f"delta must be a whole number of frames >= 1, got {delta!r}")
    delta = int(delta)
    est, transform = align_poses(est_poses, ref_poses, alignment)
    ref = np.asarray(ref_poses, dtype=np.float64)
    # all pairs: (i, i + delta) for every i; else evo's default, i = 0, delta, 2 delta, ...
    first = np.arange(len(est) - delta) if all_pairs else np.arange(0, len(est), delta)[:-1]
    if len(first) == 0:
        raise EvaluationError(f"delta = {delta} frames leaves no pose pair among {len(est)} poses")
    second = first + delta
    ref_rel = invert_rigid(ref[first]) @ ref[second]
    est_rel = invert_rigid(est[first]) @ est[second]
    error = invert_rigid(ref_rel) @ est_rel
    return RPEResult(
        delta=delta,
        all_pairs=bool(all_pairs),
        alignment=_alignment(alignment),
        transform=transform,
        translation=ErrorStats.from_errors(np.linalg.norm(error[:, :3, 3], axis=1)),
        rotation_deg=ErrorStats.from_errors(_rotation_angles_deg(error[:, :3, :3])),
        pairs=np.stack([first, second], axis=1),
    )


def cm_degree_recall(
    est_poses: np.ndarray,
    ref_poses: np.ndarray,
    *,
    thresholds: Sequence[float] = (1.0, 3.0, 5.0),
    alignment: Alignment | str = Alignment.SIM3,
    metres_per_unit: float = 1.0,
) -> CmDegreeResult:
    """Recall at ``k`` cm / ``k`` degrees for each ``k`` in ``thresholds``, after ``alignment``.

    A pose counts when its translation error is strictly below ``k`` cm and its rotation error
    strictly below ``k`` degrees. ``metres_per_unit`` converts the reference's unit to metres.
    """
    ks = tuple(float(k) for k in thresholds)
    if not ks or any(not np.isfinite(k) or k <= 0 for k in ks):
        raise ConfigError(f"cm-degree thresholds must be positive numbers, got {thresholds!r}")
    if not np.isfinite(metres_per_unit) or metres_per_unit <= 0:
        raise ConfigError(f"metres_per_unit must be > 0, got {metres_per_unit}")
    ate = absolute_trajectory_error(est_poses, ref_poses, alignment=alignment)
    t_cm = ate.translation_errors * metres_per_unit * 100.0
    r_deg = ate.rotation_errors_deg
    recall = tuple(float(np.mean((t_cm < k) & (r_deg < k))) for k in ks)
    return CmDegreeResult(ks, recall, ate.alignment, ate.transform, len(t_cm))


def _alignment(value: Alignment | str) -> Alignment:
    try:
        return Alignment(value)
    except ValueError as exc:
        choices = ", ".join(a.value for a in Alignment)
        raise ConfigError(f"unknown alignment {value!r}; choose one of {choices}") from exc


def _checked_pair(est_poses: np.ndarray, ref_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    est = np.asarray(est_poses, dtype=np.float64)
    ref = np.asarray(ref_poses, dtype=np.float64)
    for name, poses in (("estimate", est), ("reference", ref)):
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise TrajectoryError(f"{name} poses must have shape [N, 4, 4], got {poses.shape}")
        if not np.all(np.isfinite(poses)):
            raise TrajectoryError(f"{name} poses contain NaN or infinite values")
    if len(est) != len(ref):
        raise EvaluationError(
            f"{len(est)} estimated poses but {len(ref)} reference poses: "
            "match them by time first (eval.association.associate_trajectories)"
        )
    if len(est) == 0:
        raise EvaluationError("no poses to evaluate")
    return est, ref


def _rotation_angles_deg(rotations: np.ndarray) -> np.ndarray:
    """Geodesic angles [N] (degrees) of rotation matrices [N, 3, 3]; SciPy's log map, like evo."""
    return np.degrees(Rotation.from_matrix(rotations).magnitude())


def _alignment_dict(alignment: Alignment, transform: Sim3) -> dict[str, Any]:
    return {
        "method": alignment.value,
        "scale": transform.scale,
        "rotation": transform.rotation.tolist(),
        "translation": transform.translation.tolist(),
    }

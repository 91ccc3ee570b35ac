"""Trajectory plots as PNG files (matplotlib, imported on first use).

One figure: the camera centres projected on the x-y, x-z and y-z planes of the world frame
(estimate, and the reference when given), and, when per-pose errors are given, the translation
error over time. Projections on all three planes avoid guessing which axis is "up": TUM ground
truth has z up, the tracker's world frame (the first keyframe's camera) has y down. The
estimate's line is broken where poses are missing (the tracker was lost: a gap in time longer
than ``GAP_FACTOR`` median frame intervals), instead of a straight line across the gap.

The figure is built on ``matplotlib.figure.Figure`` with the Agg canvas, never through
``pyplot``: no global backend is switched, no window can open, and plotting from a worker thread
of an app is safe.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from kvtracker_sdk.errors import MissingDependencyError, TrajectoryError
from kvtracker_sdk.io.files.atomic import atomic_write
from kvtracker_sdk.io.files.trajectory import Trajectory

__all__ = ["GAP_FACTOR", "break_at_gaps", "plot_trajectory"]

GAP_FACTOR = 3.0  # a time step longer than this many median steps is a gap in the trajectory
_PLANES = ((0, 1), (0, 2), (1, 2))
_AXIS_NAMES = "xyz"


def plot_trajectory(
    path: str | os.PathLike[str],
    estimate: Trajectory,
    reference: Trajectory | None = None,
    *,
    translation_errors: np.ndarray | None = None,
    title: str | None = None,
    units: str | None = None,
) -> Path:
    """Write a PNG plot of ``estimate`` (and ``reference``) to ``path``; returns the path.

    Pass an estimate already aligned to the reference (``EvaluationReport.aligned_estimate``)
    for the two to overlap. ``translation_errors`` ([N], one per estimated pose, e.g.
    ``ATEResult.translation_errors``) adds an error-over-time panel. Written atomically.
    ``units`` names the length unit of the axes (``"m"`` once a Sim(3) alignment has scaled the
    estimate onto a metric reference); None, the default, labels them as of arbitrary scale, as
    a monocular trajectory is.
    """
    if len(estimate) == 0:
        raise TrajectoryError("cannot plot an empty trajectory")
    if translation_errors is not None and len(translation_errors) != len(estimate):
        raise TrajectoryError(
            f"{len(translation_errors)} errors for {len(estimate)} estimated poses"
        )
    figure_cls, canvas_cls = _matplotlib()
    panels = 3 if translation_errors is None else 4
    figure = figure_cls(figsize=(4.2 * panels, 4.2), layout="constrained")
    canvas_cls(figure)
    axes = figure.subplots(1, panels)
    for ax, (i, j) in zip(axes, _PLANES, strict=False):
        _plot_plane(ax, estimate, reference, i, j, units)
    axes[0].legend(loc="best", fontsize="small")
    if translation_errors is not None:
        ax = axes[3]
        times, errors = break_at_gaps(estimate.stamps, translation_errors)
        ax.plot(times - estimate.stamps[0], errors, color="tab:red", lw=1)
        ax.set_xlabel("time [s]")
        ax.set_ylabel(f"translation error {_unit_label(units)}")
        ax.set_title("error over time")
        ax.grid(True, alpha=0.3)
    if title:
        figure.suptitle(title)
    target = Path(path)
    with atomic_write(target, binary=True) as handle:
        figure.savefig(handle, format="png", dpi=110)
    return target


def break_at_gaps(
    stamps: np.ndarray, values: np.ndarray, factor: float = GAP_FACTOR
) -> tuple[np.ndarray, np.ndarray]:
    """``(stamps, values)`` with a NaN row inserted in every gap: a time step longer than
    ``factor`` times the median step (matplotlib breaks a line at NaN)."""
    stamps = np.asarray(stamps, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    if len(stamps) < 3:
        return stamps, values
    steps = np.diff(stamps)
    gaps = np.flatnonzero(steps > factor * np.median(steps)) + 1  # first index after each gap
    blank = np.full((len(gaps), *values.shape[1:]), np.nan)
    return np.insert(stamps, gaps, np.nan), np.insert(values, gaps, blank, axis=0)


def _plot_plane(
    ax: Any, estimate: Trajectory, reference: Trajectory | None, i: int, j: int,
    units: str | None,
) -> None:
    if reference is not None and len(reference):
        ref = reference.positions
        ax.plot(ref[:, i], ref[:, j], color="0.45", lw=1.2, ls="--", label="reference")
    est = estimate.positions
    _, line = break_at_gaps(estimate.stamps, est)
    ax.plot(line[:, i], line[:, j], color="tab:blue", lw=1.2, label="estimate")
    ax.scatter(est[:1, i], est[:1, j], color="tab:green", s=25, zorder=3, label="start")
    ax.set_xlabel(f"{_AXIS_NAMES[i]} {_unit_label(units)}")
    ax.set_ylabel(f"{_AXIS_NAMES[j]} {_unit_label(units)}")
    ax.set_title(f"{_AXIS_NAMES[i]}-{_AXIS_NAMES[j]}")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)


def _unit_label(units: str | None) -> str:
    return f"[{units}]" if units else "[arbitrary scale]"


def _matplotlib() -> tuple[Any, Any]:
    """``(Figure, FigureCanvasAgg)``; a typed error naming the extra if matplotlib is missing."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise MissingDependencyError.for_extra("viz", "plots need matplotlib") from exc
    return Figure, FigureCanvasAgg

"""``kvtracker eval EST GT``: score an estimated trajectory against a reference.

Both files are TUM (``t tx ty tz qx qy qz qw``) or KITTI (12 numbers a line). Poses are matched
by timestamp (nearest, within ``--max-diff`` seconds, after adding ``--offset`` to EST), the
estimate is aligned to the reference (Sim(3) by default: a monocular estimate has no scale; SE(3)
for metric estimates), then ATE, RPE and cm-degree recall are printed; ``--json`` writes them and
a plot shows the aligned trajectories with the error over time. The numbers equal evo's
(``tests/eval/test_metrics_vs_evo.py``).
"""

from __future__ import annotations

import enum
import json
from pathlib import Path
from typing import Annotated

import typer

from kvtracker_sdk.cli.failures import EXIT_CODES_EPILOG, reports_errors
from kvtracker_sdk.cli.logging_setup import CliState
from kvtracker_sdk.cli.output_checks import check_output_file
from kvtracker_sdk.errors import ConfigError, MissingDependencyError
from kvtracker_sdk.log import get_logger

__all__ = ["AlignChoice", "evaluate", "register"]

_log = get_logger(__name__)


class AlignChoice(str, enum.Enum):
    """The choices of ``--align`` (mirrors ``eval.metrics.Alignment``, which loads SciPy)."""

    SIM3 = "sim3"
    SE3 = "se3"
    NONE = "none"


def _thresholds(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError as exc:
        raise ConfigError(f"--cm-deg {text!r}: expected numbers like 1,3,5") from exc
    if not values or min(values) <= 0:
        raise ConfigError(f"--cm-deg {text!r}: expected positive numbers like 1,3,5")
    return values


@reports_errors
def evaluate(
    ctx: typer.Context,
    est: Annotated[Path, typer.Argument(help="Estimated trajectory (TUM or KITTI).", show_default=False)],
    gt: Annotated[Path, typer.Argument(help="Reference trajectory (TUM or KITTI).", show_default=False)],
    align: Annotated[AlignChoice, typer.Option(
        help="sim3 (monocular: rotation, translation, scale), se3 (metric), none.")
    ] = AlignChoice.SIM3,
    max_diff: Annotated[float, typer.Option(
        help="Largest timestamp difference of a matched pair (seconds).")] = 0.01,
    offset: Annotated[float, typer.Option(
        help="Seconds added to EST's stamps before matching.")] = 0.0,
    delta: Annotated[int, typer.Option(help="RPE: frames between the two poses of a pair.")] = 1,
    all_pairs: Annotated[bool, typer.Option(
        "--all-pairs", help="RPE: every pair (i, i+delta), not only i = 0, delta, 2 delta, ... [default: off]")] = False,
    cm_deg: Annotated[str, typer.Option(
        help="cm-degree recall thresholds k (k cm and k degrees).")] = "1,3,5",
    plot: Annotated[Path | None, typer.Option(
        help="Plot file ([viz] extra). [default: EST's name + _eval.png, beside EST]")] = None,
    no_plot: Annotated[bool, typer.Option("--no-plot", help="Do not write a plot. [default: off]")] = False,
    json_path: Annotated[Path | None, typer.Option(
        "--json", help="Also write the numbers as JSON. [default: none]")] = None,
) -> None:
    """Score EST against GT: ATE and RPE after alignment, cm-degree recall, a plot."""
    from kvtracker_sdk.eval.plots import plot_trajectory
    from kvtracker_sdk.eval.report import evaluate_trajectories
    from kvtracker_sdk.io.files.atomic import atomic_write
    from kvtracker_sdk.io.files.trajectory import read_trajectory

    state: CliState = ctx.find_root().obj
    thresholds = _thresholds(cm_deg)
    estimate, reference = read_trajectory(est), read_trajectory(gt)
    target = None if no_plot else plot or est.with_name(f"{est.stem}_eval.png")
    for path, option in ((target, "--plot"), (json_path, "--json")):
        if path is not None:
            check_output_file(path, option)
    report = evaluate_trajectories(
        estimate, reference, max_diff=max_diff, offset=offset,
        alignment=align.value, delta=delta, all_pairs=all_pairs, cm_degree_thresholds=thresholds,
    )
    written = []
    if target is not None:
        try:
            plot_trajectory(
                target, report.aligned_estimate, report.association.ref,
                translation_errors=report.ate.translation_errors,
                title=f"{est.name} vs {gt.name}: ATE RMSE {report.ate.translation.rmse:.4f}",
                # only a Sim(3) alignment brings the estimate to the reference's (metric) scale
                units="m" if align is AlignChoice.SIM3 else None,
            )
            written.append(target)
        except MissingDependencyError as error:  # the numbers matter more than the plot
            _log.warning("plot not written", reason=str(error))
    if json_path is not None:
        with atomic_write(json_path) as handle:
            json.dump({"estimate": str(est), "reference": str(gt), **report.to_dict()}, handle,
                      indent=2, allow_nan=False)
            handle.write("\n")
        written.append(json_path)
    typer.echo(report.summary())
    if written and not state.quiet:
        typer.echo("wrote " + ", ".join(str(p) for p in written))


def register(app: typer.Typer) -> None:
    app.command("eval", epilog=EXIT_CODES_EPILOG)(evaluate)

"""``kvtracker eval-many MANIFEST``: every sequence x config of a manifest, one table.

Runs on a local process pool (``--engine local``, default), on Ray (``--engine ray``: the
cluster ``ray.init`` would join, or a local one bound to 127.0.0.1) or one by one
(``--engine serial``); the three give the same numbers. Writes ``OUT/results.{csv,json}``,
``OUT/summary.md``, ``OUT/results.png`` (with matplotlib) and one folder per run.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from kvtracker_sdk.cli.failures import EXIT_CODES_EPILOG, reports_errors
from kvtracker_sdk.cli.logging_setup import CliState
from kvtracker_sdk.scale.runner import Engine

__all__ = ["eval_many", "register"]


@reports_errors
def eval_many(
    ctx: typer.Context,
    manifest: Annotated[Path, typer.Argument(
        help="Manifest (JSON or YAML): model, configs, sequences.", show_default=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path("eval_many"),
    engine: Annotated[Engine, typer.Option(
        help="serial (this process), local (process pool) or ray.")] = Engine.LOCAL,
    workers: Annotated[int, typer.Option(min=1, max=1024,
        help="Worker processes or Ray actors (each loads the model once).")] = 2,
) -> None:
    """Evaluate many sequences and configurations; print and write one table."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from kvtracker_sdk.scale.manifest import load_manifest
    from kvtracker_sdk.scale.runner import run_many

    state: CliState = ctx.find_root().obj
    plan = load_manifest(manifest)
    total = len(plan.tasks())
    columns = (TextColumn("eval-many"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
               TextColumn("{task.description}"))
    with Progress(*columns, console=state.console, disable=not state.chatty,
                  transient=True) as bar:
        task = bar.add_task("starting workers", total=total)

        def advance(done: int, _total: int, result: object) -> None:
            bar.update(task, completed=done,
                       description=f"{getattr(result, 'sequence', '')}/{getattr(result, 'config', '')}")

        result = run_many(plan, out, engine=engine, workers=workers, progress=advance)
    typer.echo(result.markdown())
    if not state.quiet:
        typer.echo(f"wrote {out / 'results.csv'}, {out / 'results.json'}, {out / 'summary.md'}")


def register(app: typer.Typer) -> None:
    app.command("eval-many", epilog=EXIT_CODES_EPILOG)(eval_many)

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
        help="serial (this process), local (process pool) or ray ([ray] extra).")] = Engine.LOCAL,
    workers: Annotated[int, typer.Option(min=1, max=1024,
        help="Worker processes or Ray actors (each loads the model once).")] = 2,
) -> None:
    """Evaluate many sequences and configurations; print and write one table.

    MANIFEST is JSON (or YAML, [yaml] extra); its paths are relative to it. "sequences": each
    has a unique "name" and either a "source" (anything `kvtracker track` reads; TUM and
    7-Scenes folders bring their ground truth, else add "ground_truth": a TUM file) or a
    "simulated" camera ("orbit_frames": N, or "ground_truth": a TUM file; needs no weights).
    "configs": named TrackerConfig overrides, every sequence runs under each. "model": the
    weights real sequences run on, loaded once per worker. Example
    (examples/manifests/tum_and_simulated.json; examples/manifests/simulated.json runs offline):

    \b
    {
      "model": {"weights": "../../weights/da3-small/model.safetensors", "dtype": "bfloat16"},
      "configs": {"default": {}, "d224": {"resolution": 224}},
      "sequences": [
        {"name": "fr2_desk", "source": "../../data/rgbd_dataset_freiburg2_desk", "frames": 300},
        {"name": "sim_orbit", "simulated": {"orbit_frames": 300, "seed": 1}}
      ]
    }
    """
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

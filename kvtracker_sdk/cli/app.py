"""The ``kvtracker`` command: a typer app assembled from one module per command group.

    kvtracker track INPUT --weights pi3.safetensors --out run/     track a video or a sequence
    kvtracker demo --out demo/                                      offline, simulated backend
    kvtracker eval run/trajectory.txt groundtruth.txt               ATE / RPE / cm-degree
    kvtracker map info office.kvmap                                 what a map file holds

Each command module exposes ``register(app)``; an optional group (``export_onnx``) is
registered only where its module exists. Command modules import the tracker,
torch and OpenCV inside their functions, so ``kvtracker --help`` stays fast.

The global options (``-v``, ``-q``, ``--log-json``) may also follow the command
(``kvtracker track ... -v``): :class:`_GlobalOptionsFirst` moves them in front of it.
"""

from __future__ import annotations

import importlib
import importlib.util
import re
from typing import Annotated, Any

import typer
from typer.core import TyperGroup

from kvtracker_sdk._version import __version__
from kvtracker_sdk.cli.failures import EXIT_CODES_EPILOG
from kvtracker_sdk.cli.logging_setup import CliState, configure_logging

__all__ = ["app", "main"]

_COMMAND_MODULES = ("track", "demo", "evaluate", "eval_many", "map_cmd", "export_cmd", "tune")
_OPTIONAL_COMMAND_MODULES = ("export_onnx",)  # registered only where the module is present
_GLOBAL_FLAGS = re.compile(r"-v+|-q+|--verbose|--quiet|--log-json")


class _GlobalOptionsFirst(TyperGroup):
    """Click parses a group's options only before the command name: this moves the global
    flags found after it (up to a ``--``) to the front, where the app callback reads them."""

    def parse_args(self, ctx: Any, args: list[str]) -> list[str]:  # typer's vendored Context
        end = args.index("--") if "--" in args else len(args)
        flags = [a for a in args[:end] if _GLOBAL_FLAGS.fullmatch(a)]
        rest = [a for a in args[:end] if not _GLOBAL_FLAGS.fullmatch(a)]
        return super().parse_args(ctx, flags + rest + args[end:])


app = typer.Typer(
    name="kvtracker",
    cls=_GlobalOptionsFirst,
    help="Real-time monocular camera and object tracking with KV-cached transformers.",
    epilog=EXIT_CODES_EPILOG,
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,  # errors are reported by failures.reports_errors
    # help texts are plain text: rich markup would eat "[default: 50]" and "[view]"
    rich_markup_mode=None,
)


def _show_version(value: bool) -> None:
    if value:
        typer.echo(f"kvtracker-sdk {__version__}")
        raise typer.Exit()


@app.callback()
def _global_options(
    ctx: typer.Context,
    verbose: Annotated[int, typer.Option(
        "--verbose", "-v", count=True, help="More logs: -v info, -vv debug (per frame).")] = 0,
    quiet: Annotated[int, typer.Option(
        "--quiet", "-q", count=True, help="Errors only; no progress bar, no summary.")] = 0,
    log_json: Annotated[bool, typer.Option(
        "--log-json", help="Logs as JSON lines on stderr (for log collectors).")] = False,
    version: Annotated[bool, typer.Option(
        "--version", callback=_show_version, is_eager=True, help="Print the version.")] = False,
) -> None:
    """Real-time monocular camera and object tracking with KV-cached transformers."""
    verbosity = verbose - quiet
    if log_json and not quiet:  # a log collector wants the run's events, not warnings only
        verbosity = max(verbosity, 1)
    state = CliState(verbosity=verbosity, log_json=log_json)
    configure_logging(state)
    ctx.obj = state


def _register_commands() -> None:
    for name in _COMMAND_MODULES:
        importlib.import_module(f"kvtracker_sdk.cli.{name}").register(app)
    for name in _OPTIONAL_COMMAND_MODULES:
        if importlib.util.find_spec(f"kvtracker_sdk.cli.{name}") is not None:
            importlib.import_module(f"kvtracker_sdk.cli.{name}").register(app)


_register_commands()


def main() -> None:
    """Console-script entry point (``kvtracker``); exit codes: ``failures.EXIT_CODES``."""
    app(prog_name="kvtracker")

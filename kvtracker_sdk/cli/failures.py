"""Exit codes and error reporting of the ``kvtracker`` command.

Every command is wrapped by :func:`reports_errors`: an SDK error becomes one ``error:`` line on
stderr, a ``hint:`` line saying what to do, and a documented exit code (:class:`ExitCode`, listed
in every ``--help`` epilog by :data:`EXIT_CODES_EPILOG`). Anything else is a bug: one line asking
for a report (the traceback with ``-v``), exit code 1. Scripts can rely on the codes; the
messages are for people.
"""

from __future__ import annotations

import enum
import functools
import traceback
from collections.abc import Callable
from typing import Any, TypeVar

import typer

from kvtracker_sdk import errors

__all__ = ["EXIT_CODES", "EXIT_CODES_EPILOG", "ExitCode", "exit_code_for", "reports_errors"]


class ExitCode(enum.IntEnum):
    """What the ``kvtracker`` process returns (meanings in :data:`EXIT_CODES`)."""

    OK = 0
    INTERNAL = 1
    USAGE = 2
    INPUT = 3
    WEIGHTS = 4
    DEPENDENCY = 5
    MAP = 6
    EVALUATION = 7
    CONFIG = 8
    BACKEND = 9
    OUTPUT = 10
    INTERRUPTED = 130


EXIT_CODES: dict[int, str] = {
    ExitCode.OK: "success",
    ExitCode.INTERNAL: "internal error (a bug: rerun with -v and report the traceback)",
    ExitCode.USAGE: "bad command-line usage",
    ExitCode.INPUT: "unusable input (frames, masks, box, trajectory file)",
    ExitCode.WEIGHTS: "weights not found or not matching the model",
    ExitCode.DEPENDENCY: "an optional extra is missing (pip install 'kvtracker-sdk[...]')",
    ExitCode.MAP: "map file error (--load-map or map info: missing, not a map, another model)",
    ExitCode.EVALUATION: "trajectories cannot be compared",
    ExitCode.CONFIG: "invalid configuration",
    ExitCode.BACKEND: "backend error or backend mismatch",
    ExitCode.OUTPUT: "an output cannot be written (--out, --save-map, --rerun: missing folder, "
    "permissions, disk full)",
    ExitCode.INTERRUPTED: "interrupted (the map and the outputs of the processed frames are "
    "written)",
}

EXIT_CODES_EPILOG = "Exit codes: " + "; ".join(
    f"{int(code)} {text.split(' (')[0]}" for code, text in EXIT_CODES.items()
)

# Most specific first: EvaluationError is an InputError, WeightsNotFoundError a ModelError, ...
_CODES: tuple[tuple[type[BaseException], ExitCode, str], ...] = (
    (
        errors.WeightsNotFoundError,
        ExitCode.WEIGHTS,
        "pass a local checkpoint: --weights /path/to/model.safetensors (or the folder holding "
        "it); download it once on a machine with network access. Offline, try `kvtracker demo`.",
    ),
    (
        errors.CheckpointMismatchError,
        ExitCode.WEIGHTS,
        "the checkpoint does not fit the model: check that --weights points to a Pi3 checkpoint",
    ),
    (errors.ModelError, ExitCode.WEIGHTS, "check the --weights file"),
    (
        errors.MissingDependencyError,
        ExitCode.DEPENDENCY,
        "install the extra the message names, e.g. pip install 'kvtracker-sdk[viz]'",
    ),
    (
        errors.EvaluationError,
        ExitCode.EVALUATION,
        "check that both files use the same clock: widen --max-diff or set --offset",
    ),
    (
        errors.TrajectoryError,
        ExitCode.INPUT,
        "trajectory files are TUM (t tx ty tz qx qy qz qw) or KITTI (12 numbers a line)",
    ),
    (
        errors.SourceError,
        ExitCode.INPUT,
        "INPUT is a video file, a folder of images, a TUM folder (rgb.txt) or a 7-Scenes "
        "sequence folder",
    ),
    (errors.InputError, ExitCode.INPUT, "check the frames, masks and --bbox you passed"),
    (
        errors.MapError,
        ExitCode.MAP,
        "inspect the file with `kvtracker map info PATH`; a map loads only with the weights "
        "that made it",
    ),
    (
        errors.OutputError,
        ExitCode.OUTPUT,
        "choose an output path in an existing folder you can write to (checked before the run)",
    ),
    (errors.ConfigError, ExitCode.CONFIG, "see `kvtracker COMMAND --help` for valid values"),
    (
        errors.BackendMismatchError,
        ExitCode.BACKEND,
        "both backends (or the backend and the map) must come from the same weights",
    ),
    (errors.BackendError, ExitCode.BACKEND, "rerun with -v for details"),
    (errors.KVTrackerError, ExitCode.INTERNAL, "rerun with -v for details"),
    # after the SDK errors: WeightsNotFoundError and MapIOError are OSErrors too
    (OSError, ExitCode.OUTPUT, "check that the output folder is writable and has free space"),
)


def exit_code_for(error: BaseException) -> tuple[ExitCode, str]:
    """(exit code, hint) for an exception; unknown exceptions are internal errors."""
    for kind, code, hint in _CODES:
        if isinstance(error, kind):
            return code, hint
    return ExitCode.INTERNAL, "this is a bug: rerun with -v and report the traceback"


F = TypeVar("F", bound=Callable[..., Any])


def reports_errors(command: F) -> F:
    """Wrap a typer command: SDK errors -> one line, a hint, and the documented exit code.

    With ``-v`` (read through the command's ``ctx: typer.Context`` argument) the traceback
    comes first.
    """

    @functools.wraps(command)  # typer reads the wrapped signature through __wrapped__
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return command(*args, **kwargs)
        except (typer.Exit, typer.Abort):
            raise
        except KeyboardInterrupt as exc:  # outside the frame loop (which handles its own)
            typer.echo("interrupted", err=True)
            raise typer.Exit(int(ExitCode.INTERRUPTED)) from exc
        except Exception as exc:
            code, hint = exit_code_for(exc)
            if _verbosity(kwargs) > 0:
                typer.echo("".join(traceback.format_exception(exc)).rstrip(), err=True)
            typer.echo(f"error: {_one_line(exc)}", err=True)
            typer.echo(f"hint: {hint}", err=True)
            raise typer.Exit(int(code)) from exc

    return wrapper  # type: ignore[return-value]


def _one_line(error: BaseException) -> str:
    text = " ".join(str(error).split()) or type(error).__name__
    return text if isinstance(error, errors.KVTrackerError) else f"{type(error).__name__}: {text}"


def _verbosity(kwargs: dict[str, Any]) -> int:
    """The -v count the app callback stored in the root context, reached through the command's
    ``ctx`` argument (typer passes it by name; 0 without one)."""
    context = kwargs.get("ctx")
    state = getattr(context.find_root(), "obj", None) if context is not None else None
    return int(getattr(state, "verbosity", 0))

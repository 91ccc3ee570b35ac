"""Exit codes and error reporting of the ``kvtracker`` command.

Every command is wrapped by :func:`reports_errors`: an SDK error becomes an ``error:`` line on
stderr (a message of several lines, such as a manifest's invalid fields, follows it indented), a
``hint:`` line saying what fits this error, and a documented exit code (:class:`ExitCode`, listed
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
from kvtracker_sdk.cli import output_checks

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
    SOURCE = 11
    INTERRUPTED = 130


EXIT_CODES: dict[int, str] = {
    ExitCode.OK: "success",
    ExitCode.INTERNAL: "internal error (a bug: rerun with -v and report the traceback)",
    ExitCode.USAGE: "bad command-line usage",
    ExitCode.INPUT: "unusable input (frames, masks, box, trajectory file)",
    ExitCode.WEIGHTS: "weights not found or not matching the model",
    ExitCode.DEPENDENCY: 'an optional extra is missing (pip install -e ".[EXTRA]" in the clone)',
    ExitCode.MAP: "map file error (--load-map or map info: missing, not a map, another model)",
    ExitCode.EVALUATION: "trajectories cannot be compared",
    ExitCode.CONFIG: "invalid configuration",
    ExitCode.BACKEND: "backend error or backend mismatch",
    ExitCode.OUTPUT: "an output cannot be written (--out, --save-map, --rerun: missing folder, "
    "permissions, disk full)",
    ExitCode.SOURCE: "the input cannot be opened (no such camera, unreachable stream, missing "
    "path); nothing is written",
    ExitCode.INTERRUPTED: "interrupted (the map and the outputs of the processed frames are "
    "written)",
}

EXIT_CODES_EPILOG = "Exit codes: " + "; ".join(
    f"{int(code)} {text.split(' (')[0]}" for code, text in EXIT_CODES.items()
)

# Most specific first: EvaluationError is an InputError, WeightsNotFoundError a ModelError, ...
# A hint is text, or a function of the error when the error itself says what fits (which camera,
# which extra); an error's own ``hint`` (set where it was raised) comes before either.
Hint = str | Callable[[BaseException], str]

_INPUT_KINDS = ("INPUT is a video file, a folder of images, a TUM folder (rgb.txt), a 7-Scenes "
                "sequence folder, a camera index (0) or a stream URL (rtsp://...)")


def _source_open_hint(error: BaseException) -> str:
    kind = getattr(error, "kind", "path")
    if kind == "camera":
        return ("check the camera index (Linux: ls /dev/video*; the first camera is 0), that no "
                "other program is using the camera, and that you may open it (Linux: the video "
                "group); a number is read as a camera only when no file or folder has that name")
    if kind == "stream":
        return ("check the URL (scheme, host, port, path) and that the stream plays from this "
                "machine (e.g. ffplay URL); OpenCV reads rtsp/http streams through its FFmpeg "
                "backend; -v logs OpenCV's own messages")
    if kind == "video":
        return ("OpenCV cannot decode this file: convert it (e.g. ffmpeg -i IN -c:v libx264 "
                "OUT.mp4) or pass a folder of its frames")
    return f"check the path: {_INPUT_KINDS}"


def _missing_extra_hint(error: BaseException) -> str:
    extra = getattr(error, "extra", None)
    if extra:
        return errors.install_command(extra)
    return 'install the extra the message names: pip install -e ".[EXTRA]" in your clone'


_CODES: tuple[tuple[type[BaseException], ExitCode, Hint], ...] = (
    (
        errors.WeightsNotFoundError,
        ExitCode.WEIGHTS,
        "pass a local checkpoint: --weights /path/to/model.safetensors (or the folder holding "
        "it); download it once on a machine with network access. Offline, try `kvtracker demo`.",
    ),
    (
        errors.CheckpointMismatchError,
        ExitCode.WEIGHTS,
        "the checkpoint does not fit the model: check that --weights is a Pi3 or Depth Anything 3 "
        "checkpoint (the message lists the keys that differ)",
    ),
    (errors.ModelError, ExitCode.WEIGHTS, "check the --weights file"),
    (errors.MissingDependencyError, ExitCode.DEPENDENCY, _missing_extra_hint),
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
    (errors.SourceOpenError, ExitCode.SOURCE, _source_open_hint),
    (
        errors.FrameDecodeError,
        ExitCode.INPUT,
        "a frame file is damaged or not an image: replace it, or pass --on-bad-frame skip to go "
        "on without it",
    ),
    (errors.IntrinsicsError, ExitCode.INPUT, "pass the camera: --camera FILE (JSON/YAML or ROS "
     "CameraInfo) or --intrinsics fx,fy,cx,cy,W,H; --force-fitted-focal exports the fit anyway"),
    (errors.SourceError, ExitCode.INPUT, _INPUT_KINDS),
    (
        errors.ImageShapeError,
        ExitCode.INPUT,
        "every frame of a run must be an HxWx3 colour image of the first frame's size",
    ),
    (
        errors.ResolutionChangedError,
        ExitCode.INPUT,
        "every frame of a run must have the first frame's size (with --load-map: the size the "
        "map's frames had); resize the frames or start a new run",
    ),
    (errors.DepthError, ExitCode.INPUT, "--depth images must match their frames (same size, "
     "registered); integer images need --depth-scale (metres per unit)"),
    (errors.GravityError, ExitCode.INPUT, "gravity is 3 finite numbers in the camera frame "
     "(an accelerometer reading), not near zero"),
    (errors.MaskError, ExitCode.INPUT, "masks are images of the frames' size, one per frame "
     "(--masks DIR, natural order); each must select some pixels"),
    (errors.BBoxError, ExitCode.INPUT, "--bbox is x0,y0,x1,y1 in pixels of the frame, "
     "x0 < x1 and y0 < y1, inside the image"),
    (errors.InputError, ExitCode.INPUT, "check the frames, masks and --bbox you passed"),
    (
        errors.MapIOError,
        ExitCode.MAP,
        "check that the map path exists and is a readable file",
    ),
    (
        errors.MapVersionError,
        ExitCode.MAP,
        "the map's format version is newer than this SDK reads: upgrade kvtracker-sdk",
    ),
    (
        errors.MapModelMismatchError,
        ExitCode.MAP,
        "a map loads only with the weights, model family and resolution that made it: pass "
        "those (the message names both)",
    ),
    (
        errors.MapPreprocessingError,
        ExitCode.MAP,
        "track against the map as it is, or add --rebuild-map to extend it with this SDK's "
        "preprocessing",
    ),
    (
        errors.MapError,
        ExitCode.MAP,
        "the file is not a complete .kvmap (another format, truncated or damaged): save the map "
        "again or use another copy",
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
            own = getattr(error, "hint", None) if isinstance(error, errors.KVTrackerError) else None
            return code, own or (hint(error) if callable(hint) else hint)
    return ExitCode.INTERNAL, "this is a bug: rerun with -v and report the traceback"


F = TypeVar("F", bound=Callable[..., Any])


def reports_errors(command: F) -> F:
    """Wrap a typer command: SDK errors -> one line, a hint, and the documented exit code.

    With ``-v`` (read through the command's ``ctx: typer.Context`` argument) the traceback
    comes first.
    """

    @functools.wraps(command)  # typer reads the wrapped signature through __wrapped__
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        output_checks.forget_created_folders()
        try:
            return command(*args, **kwargs)
        except typer.Exit as exc:
            if exc.exit_code != 0:
                output_checks.remove_created_folders_if_empty()
            raise
        except typer.Abort:
            output_checks.remove_created_folders_if_empty()
            raise
        except KeyboardInterrupt as exc:  # outside the frame loop (which handles its own)
            output_checks.remove_created_folders_if_empty()
            typer.echo("interrupted", err=True)
            raise typer.Exit(int(ExitCode.INTERRUPTED)) from exc
        except Exception as exc:
            output_checks.remove_created_folders_if_empty()  # no empty --out after an early failure
            code, hint = exit_code_for(exc)
            if _verbosity(kwargs) > 0:
                typer.echo("".join(traceback.format_exception(exc)).rstrip(), err=True)
            first, *more = _message_lines(exc)
            typer.echo(f"error: {first}", err=True)
            for line in more:  # e.g. one line per invalid field of a manifest
                typer.echo(f"  {line}", err=True)
            typer.echo(f"hint: {hint}", err=True)
            raise typer.Exit(int(code)) from exc

    return wrapper  # type: ignore[return-value]


def _message_lines(error: BaseException) -> list[str]:
    """The message as lines (whitespace inside each line collapsed, empty lines dropped); a
    foreign exception is prefixed with its type."""
    lines = [" ".join(line.split()) for line in str(error).splitlines()]
    lines = [line for line in lines if line] or [type(error).__name__]
    if not isinstance(error, errors.KVTrackerError):
        lines[0] = f"{type(error).__name__}: {lines[0]}"
    return lines


def _verbosity(kwargs: dict[str, Any]) -> int:
    """The -v count the app callback stored in the root context, reached through the command's
    ``ctx`` argument (typer passes it by name; 0 without one)."""
    context = kwargs.get("ctx")
    state = getattr(context.find_root(), "obj", None) if context is not None else None
    return int(getattr(state, "verbosity", 0))

"""``kvtracker tune``: measure the runtimes, dtypes and thread counts here and keep the fastest.

    kvtracker tune --weights da3-small --resolution 224 --keyframes 32
    kvtracker tune --weights pi3.safetensors --runtime torch --runtime openvino --seconds 10
    kvtracker track video.mp4 --weights da3-small --resolution 224 --max-keyframes 32  # uses it

The candidates (``backends/autotune.py``) are timed on the weights, at the resolution and map
size given, for a few seconds (the closest raced in paired rounds for up to as long again); the
fastest whose pose deviation from fp32 stays within the torch
bf16 deviation is kept per machine and model (``io/files/tune_cache.py``). ``kvtracker track``'s
default ``--backend auto`` then uses that choice (``auto_choice``) unless ``--dtype`` or
``--threads`` is given; without a kept choice it runs PyTorch as before and says how to tune.
OpenVINO / ONNX candidates serve an export of the weights (made once: minutes for a full model).
"""

from __future__ import annotations

import importlib.util
import json
from collections.abc import Callable
from typing import TYPE_CHECKING, Annotated

import typer

from kvtracker_sdk.cli.failures import EXIT_CODES_EPILOG, reports_errors
from kvtracker_sdk.cli.logging_setup import CliState
from kvtracker_sdk.cli.number_options import finite
from kvtracker_sdk.cli.progress import busy
from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.runs.backends import DEFAULT_WEIGHTS, BackendKind, open_backend

if TYPE_CHECKING:
    from kvtracker_sdk.backends.autotune import Candidate, TuneProblem
    from kvtracker_sdk.backends.base import Backend

__all__ = ["auto_choice", "installed_runtimes", "register", "tune"]

_log = get_logger(__name__)
_PACKAGES = {"torch": "torch", "onnx": "onnxruntime", "openvino": "openvino"}


def installed_runtimes() -> list[str]:
    """The runtimes whose package is installed (torch always: it holds the cache)."""
    return [name for name, package in _PACKAGES.items()
            if name == "torch" or importlib.util.find_spec(package) is not None]  # fmt: skip


def _opener(weights: str) -> Callable[[Candidate], Backend]:
    def open_candidate(candidate: Candidate) -> Backend:
        threads = None if candidate.runtime == "onnx" else candidate.threads
        return open_backend(
            BackendKind(candidate.runtime), weights, dtype=candidate.dtype, threads=threads
        )

    return open_candidate


def _frame_size(text: str) -> tuple[int, int]:
    """``"640x480"`` (W x H, as cameras say it) -> (H, W)."""
    try:
        width, height = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--frame-size must be WxH such as 640x480, got {text!r}") from None
    if width < 1 or height < 1:
        raise ConfigError(f"--frame-size must be positive, got {text!r}")
    return height, width


@reports_errors
def tune(
    ctx: typer.Context,
    weights: Annotated[str, typer.Option(
        help="Checkpoint (a model name, .safetensors file, folder or hub id).")] = DEFAULT_WEIGHTS,
    resolution: Annotated[int | None, typer.Option(
        help="The tracker's --resolution d (224, 308, 504, 518). [default: the family's]")] = None,
    frame_size: Annotated[str, typer.Option(
        help="Input frame size WxH (the model size follows as the tracker resizes).")] = "640x480",
    keyframes: Annotated[int, typer.Option(min=1, max=1024,
        help="Map size tuned for: the tracker's keyframe budget (--max-keyframes).")] = 32,
    runtime: Annotated[list[str] | None, typer.Option(
        help="Runtimes to try (torch, onnx, openvino; repeat the option). [default: installed]")
    ] = None,
    seconds: Annotated[float, typer.Option(min=0.1, max=3600, callback=finite, help="Timing budget; racing the closest candidates may take as long again (the map pass comes on top).")] = 5.0,
    as_json: Annotated[bool, typer.Option("--json", help="Print the result as JSON. [default: off]")] = False,
) -> None:
    """Time the runtimes, dtypes and thread counts on these weights here; keep the fastest."""
    from kvtracker_sdk.backends.autotune import RUNTIMES, TuneProblem, default_candidates
    from kvtracker_sdk.backends.autotune import tune as run_tuner
    from kvtracker_sdk.io.files.tune_cache import choice_key, remember_choice
    from kvtracker_sdk.threads import usable_cores

    state: CliState = ctx.find_root().obj
    runtimes = runtime or installed_runtimes()
    unknown = sorted(set(runtimes) - set(RUNTIMES))
    if unknown:
        raise ConfigError(f"unknown runtime(s) {unknown}; choose from {list(RUNTIMES)}")
    if "torch" not in runtimes:
        runtimes = ["torch", *runtimes]  # the fp32 and bf16 references
    if seconds <= 0:
        raise ConfigError(f"--seconds must be positive, got {seconds}")
    problem = TuneProblem(keyframes, resolution, _frame_size(frame_size))
    candidates = default_candidates(runtimes, usable_cores())
    text = f"tuning {len(candidates)} candidates on {weights} (exports are made once: minutes)"
    with busy(state, text, announce=True):
        result = run_tuner(_opener(weights), candidates, problem, seconds=seconds)
    path = remember_choice(choice_key(weights, problem), result)
    if as_json:
        typer.echo(json.dumps(json.loads(path.read_text()), indent=1))
        return
    if not state.quiet:
        typer.echo(result.table())
        typer.echo(f"\nchosen: {result.reason}")
        typer.echo(f"kept in {path} (kvtracker track --backend auto uses it)")


def auto_choice(
    weights: str, *, resolution: int | None, keyframes: int
) -> tuple[BackendKind, str, int | None, str]:
    """``--backend auto``: (runtime, dtype, threads, why) from the kept choice for these weights
    and this problem on this machine, else PyTorch float32 with automatic threads."""
    from kvtracker_sdk.backends.autotune import TuneProblem
    from kvtracker_sdk.io.files.tune_cache import cached_choice, choice_key

    problem: TuneProblem = TuneProblem(keyframes, resolution)
    kept = cached_choice(choice_key(weights, problem))
    if kept is None:
        why = ("no tuned choice for these weights, resolution and keyframe budget on this "
               f"machine: torch float32 (run `kvtracker tune --weights {weights} --resolution "
               f"{resolution or 'D'} --keyframes {keyframes}` to choose by measurement)")  # fmt: skip
        _log.info("backend auto", choice="torch-float32", reason=why)
        return BackendKind.TORCH, "float32", None, why
    candidate, reason = kept
    _log.info("backend auto", choice=candidate.name, reason=reason)
    return BackendKind(candidate.runtime), candidate.dtype, candidate.threads, reason


def register(app: typer.Typer) -> None:
    app.command("tune", epilog=EXIT_CODES_EPILOG)(tune)

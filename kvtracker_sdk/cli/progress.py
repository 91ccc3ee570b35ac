"""The live progress bar of ``kvtracker track`` / ``demo``: frames, FPS, tracking state, keyframes;
and ``busy``, the spinner shown over any other long step (loading or exporting weights, saving).

Drawn with rich (installed with typer) on stderr, only when stderr is a terminal and the run is
not ``-q``: piped or captured output gets the final summary alone, not a stream of redraws.
Messages printed while the bar is live (``note``) appear above it.
"""

from __future__ import annotations

import collections
import contextlib
import time
from collections.abc import Iterator
from types import TracebackType

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from kvtracker_sdk.cli.logging_setup import CliState
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.types import FrameResult, TrackingState

__all__ = ["FrameProgress", "busy"]

_log = get_logger(__name__)

_STATE_STYLES = {
    TrackingState.INIT: "dim",
    TrackingState.MAPPING: "cyan",
    TrackingState.TRACKING: "green",
    TrackingState.RELOCALIZING: "yellow",
}
_FPS_WINDOW = 30  # frames in the moving FPS window: smooth, yet reacts within a second at 30 Hz


class FrameProgress:
    """Context manager: ``update(result)`` after every frame, ``note(text)`` for messages."""

    def __init__(
        self, console: Console, total: int | None, *, label: str, enabled: bool = True
    ) -> None:
        self.console = console
        self.enabled = enabled and console.is_terminal
        self._ticks: collections.deque[float] = collections.deque(maxlen=_FPS_WINDOW + 1)
        self._progress = Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[fps]:>5.1f} FPS"),
            TextColumn("{task.fields[state]}"),
            TextColumn("kf {task.fields[keyframes]}"),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
            console=console,
            disable=not self.enabled,
            transient=False,
        )
        self._task: TaskID = self._progress.add_task(
            label, total=total, fps=0.0, state="", keyframes=0
        )

    def __enter__(self) -> FrameProgress:
        self._progress.start()
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        self._progress.stop()

    @property
    def fps(self) -> float:
        """Frames per second over the last ``_FPS_WINDOW`` frames (0 before two frames)."""
        if len(self._ticks) < 2:
            return 0.0
        return (len(self._ticks) - 1) / max(self._ticks[-1] - self._ticks[0], 1e-9)

    def update(self, result: FrameResult, num_keyframes: int) -> None:
        self._ticks.append(time.perf_counter())
        style = _STATE_STYLES[result.state]
        self._progress.update(
            self._task,
            advance=1,
            fps=self.fps,
            state=f"[{style}]{result.state.value:<12}[/]",
            keyframes=num_keyframes,
        )

    def note(self, text: str) -> None:
        """Print a line (above the live bar when there is one)."""
        self.console.print(text, highlight=False)


@contextlib.contextmanager
def busy(state: CliState, text: str, *, announce: bool = False) -> Iterator[None]:
    """A spinner saying ``text`` while the block runs (stderr a terminal, not -q/--log-json).

    ``announce``: a step that can take minutes also prints ``text`` as one plain line when
    stderr is not a terminal, so that a log of the run does not fall silent. Logged at INFO.
    """
    _log.info(text)
    if not state.chatty:
        yield
        return
    if not state.console.is_terminal:
        if announce:
            state.console.print(text, highlight=False, markup=False)
        yield
        return
    with state.console.status(text):
        yield

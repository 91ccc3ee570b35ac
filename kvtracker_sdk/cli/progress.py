"""The live progress bar of ``kvtracker track`` / ``demo``: frames, FPS, tracking state, keyframes.

Drawn with rich (installed with typer) on stderr, only when stderr is a terminal and the run is
not ``-q``: piped or captured output gets the final summary alone, not a stream of redraws.
Messages printed while the bar is live (``note``) appear above it.
"""

from __future__ import annotations

import collections
import time
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

from kvtracker_sdk.types import FrameResult, TrackingState

__all__ = ["FrameProgress"]

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

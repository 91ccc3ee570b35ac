"""``--view`` and ``--ros2-bag``: outputs that follow a ``track`` / ``demo`` run as it happens.

Both need an optional extra; neither is needed to finish a run. Without viser, ``--view`` says
so and the run goes on. Without rosbags, ``--ros2-bag`` says so at the start, the run and every
other output are still written, and the command then exits with code 5 (an output it was asked
for is missing). A bag is kept when the run ends, is interrupted (Ctrl-C) or stops at a bad frame (the frames so
far), and discarded when the run fails on a bug.
"""

from __future__ import annotations

import contextlib
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from kvtracker_sdk.cli.logging_setup import CliState
from kvtracker_sdk.cli.session import OutputOptions
from kvtracker_sdk.errors import KVTrackerError, MissingDependencyError
from kvtracker_sdk.runs.run_loop import InputFrame
from kvtracker_sdk.types import FrameResult

if TYPE_CHECKING:
    from kvtracker_sdk.tracking.facade.tracker import Tracker

__all__ = ["FrameObserver", "LiveOptions", "LiveOutputs", "live_outputs"]

FrameObserver = Callable[[InputFrame, FrameResult], None]


@dataclass(frozen=True)
class LiveOptions:
    """What the user asked for: a live view (and its port), a ROS 2 bag folder."""

    view: bool = False
    view_port: int = 8080
    ros2_bag: Path | None = None


@dataclass
class LiveOutputs:
    """The open viewer / bag writer and the per-frame calls that feed them."""

    observers: list[FrameObserver] = field(default_factory=list)
    viewer: Any = None
    bag: Any = None
    missing: list[str] = field(default_factory=list)  # messages of the extras not installed

    def around(self, options: OutputOptions) -> OutputOptions:
        """``options`` with these outputs' per-frame calls added."""
        return replace(options, frame_observers=(*options.frame_observers, *self.observers))


@contextmanager
def live_outputs(options: LiveOptions, tracker: Tracker, state: CliState) -> Iterator[LiveOutputs]:
    """Open what ``options`` ask for around a run of ``tracker``; close it afterwards."""
    live = LiveOutputs()
    subscriptions: list[Any] = []
    try:
        if options.view:
            _open_viewer(live, options, tracker, state, subscriptions)
        if options.ros2_bag is not None:
            _open_bag(live, options.ros2_bag, tracker, state, subscriptions)
        yield live
    except BaseException as exc:
        # the run ended early but its frames are sound (Ctrl-C: Exit(130); a bad frame or a map
        # that could not be saved: an SDK error after the outputs were written): keep the bag
        sound = isinstance(exc, typer.Exit | KeyboardInterrupt | KVTrackerError)
        _close(live, tracker, subscriptions, state, keep=sound, hold=False)
        raise
    _close(live, tracker, subscriptions, state, keep=True, hold=True)
    if live.missing:
        raise MissingDependencyError("; ".join(live.missing))


def _open_viewer(live: LiveOutputs, options: LiveOptions, tracker: Tracker, state: CliState,
                 subscriptions: list[Any]) -> None:
    try:
        from kvtracker_sdk.viz.live_viewer import Viewer

        live.viewer = Viewer(port=options.view_port)
    except MissingDependencyError as exc:
        typer.echo(f"--view: {exc}; tracking without the live view", err=True)
        return
    subscriptions += live.viewer.attach(tracker)
    live.observers.append(lambda f, r: live.viewer.log_frame(f.image, r, mask=f.mask))
    if not state.quiet:
        typer.echo(f"live view  {live.viewer.url}", err=True)


def _open_bag(live: LiveOutputs, path: Path, tracker: Tracker, state: CliState,
              subscriptions: list[Any]) -> None:
    try:
        from kvtracker_sdk.io.exports.ros2_bag import Ros2BagWriter

        live.bag = Ros2BagWriter(path)
    except MissingDependencyError as exc:
        typer.echo(f"--ros2-bag: {exc}; the other outputs are still written", err=True)
        live.missing.append(f"--ros2-bag {path} not written: {exc}")
        return
    bag = live.bag
    bag.write_map(tracker.keyframe_map)  # a map loaded before the run
    subscriptions.append(
        tracker.events.on_map_updated(lambda _e: bag.write_map(tracker.keyframe_map)))
    live.observers.append(lambda f, r: bag.write_frame(r, f.image.shape[1], f.image.shape[0]))


def _close(live: LiveOutputs, tracker: Tracker, subscriptions: list[Any], state: CliState,
           *, keep: bool, hold: bool) -> None:
    for subscription in subscriptions:
        tracker.events.unregister(subscription)
    if live.bag is not None:
        if keep:
            live.bag.write_map(tracker.keyframe_map)  # the final map
        path = live.bag.close(keep=keep)
        if path is not None and not state.quiet:
            typer.echo(f"ros2 bag   {path}", err=True)
    if live.viewer is not None:
        if hold and state.chatty and sys.stdin.isatty():  # a finished run: let the user look
            _hold(live.viewer.url)
        live.viewer.close()


def _hold(url: str) -> None:
    """Keep serving the finished run's view until the user presses Ctrl-C."""
    typer.echo(f"live view  {url} stays open: Ctrl-C to quit", err=True)
    with contextlib.suppress(KeyboardInterrupt):
        threading.Event().wait()

"""The frame loop every entry point runs (``kvtracker track`` and ``demo``, ``eval-many`` on each
engine, an app's own loop through ``runs.track``), and what it records.

``run_frames`` pushes frames into a tracker, feeds an optional progress display and the optional
per-frame hooks (the CLI's rerun sink, live view), and returns a :class:`RunRecord`: every frame result, every state change, and per-stage timings
(``source``: reading or rendering the frame; the tracker's own ``preprocess``/``track``/``map``;
``sink``: rerun logging). A Ctrl-C ends the loop cleanly: the first one lets the current frame
finish (the tracker is never cut off in the middle of a frame), a second one stops at once; the
record says ``interrupted`` and the caller still writes the outputs of the frames processed.

A bad frame (an ``InputError``: undecodable, another size, a bad mask) either stops the run
(``BadFramePolicy.STOP``: the record keeps the error, the caller writes the outputs so far and
then reports it) or is skipped and counted (``SKIP``). Any other exception also ends the loop
with the record intact (``failure``), so that whatever fails, the frames tracked are kept.
"""

from __future__ import annotations

import enum
import math
import signal
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from types import FrameType
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from kvtracker_sdk.errors import InputError
from kvtracker_sdk.io.files.trajectory import Trajectory
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.types import FrameResult, TrackingState

if TYPE_CHECKING:  # the tracker pulls in torch: imported by the commands when they run
    from kvtracker_sdk.tracking.core.events import KeyframeEvent, StateChangeEvent
    from kvtracker_sdk.tracking.facade.tracker import Tracker

__all__ = [
    "BadFrame",
    "BadFramePolicy",
    "InputFrame",
    "ProgressDisplay",
    "RunRecord",
    "StageStats",
    "run_frames",
]

_log = get_logger(__name__)
_BAD_FRAMES_LISTED = 50  # run.json lists the first bad frames; the count covers all of them


class ProgressDisplay(Protocol):
    """What the loop tells a progress display after every frame (the CLI's progress bar)."""

    def update(self, result: FrameResult, num_keyframes: int) -> None: ...


class BadFramePolicy(str, enum.Enum):
    """What ``--on-bad-frame`` does with a frame the tracker cannot use."""

    STOP = "stop"  # end the run there (outputs so far written, exit code 3)
    SKIP = "skip"  # leave the frame out, count it, go on


@dataclass(frozen=True)
class InputFrame:
    """One frame for the tracker: HxWx3 uint8 RGB, its time in seconds, optional mask or box.

    ``error`` set: the source could not produce this frame (``image`` is then empty).
    """

    image: np.ndarray
    timestamp: float
    mask: np.ndarray | None = None
    bbox: tuple[float, float, float, float] | None = None
    error: InputError | None = None
    depth: np.ndarray | None = None  # registered depth image (raw units or metres), if any
    depth_scale: float | None = None  # metres per raw depth unit


@dataclass(frozen=True)
class BadFrame:
    """A frame that could not be used: its position in the run, its stamp, and why."""

    position: int
    timestamp: float | None
    error: str

    def to_dict(self) -> dict[str, Any]:
        return {"position": self.position, "timestamp": self.timestamp, "error": self.error}


@dataclass(frozen=True)
class StageStats:
    """Wall time of one stage over the frames that ran it (milliseconds)."""

    count: int
    mean_ms: float
    p95_ms: float
    total_ms: float

    @classmethod
    def of(cls, samples: list[float]) -> StageStats:
        values = np.asarray(samples, dtype=np.float64)
        return cls(len(values), float(values.mean()), float(np.percentile(values, 95)),
                   float(values.sum()))

    def to_dict(self) -> dict[str, float | int]:
        return {"count": self.count, "mean_ms": round(self.mean_ms, 3),
                "p95_ms": round(self.p95_ms, 3), "total_ms": round(self.total_ms, 3)}


@dataclass
class RunRecord:
    """Everything a run produced besides the map (which the tracker holds)."""

    results: list[FrameResult] = field(default_factory=list)
    state_changes: list[StateChangeEvent] = field(default_factory=list)
    keyframes: list[KeyframeEvent] = field(default_factory=list)
    stage_samples: dict[str, list[float]] = field(default_factory=dict)
    wall_seconds: float = 0.0
    interrupted: bool = False
    initial_state: TrackingState = TrackingState.INIT  # RELOCALIZING after loading a map
    bad_frame_policy: BadFramePolicy = BadFramePolicy.STOP
    bad_frames: list[BadFrame] = field(default_factory=list)
    failure: Exception | None = None  # what ended the run early (a bad frame under STOP, ...)
    num_keyframes: int = 0  # the map's keyframes once the loop ended (rebuilds collected)

    def add_sample(self, stage: str, milliseconds: float) -> None:
        self.stage_samples.setdefault(stage, []).append(milliseconds)

    @property
    def num_frames(self) -> int:
        return len(self.results)

    @property
    def fps(self) -> float:
        return self.num_frames / self.wall_seconds if self.wall_seconds > 0 else 0.0

    def stage_stats(self) -> dict[str, StageStats]:
        return {name: StageStats.of(v) for name, v in self.stage_samples.items() if v}

    def frames_per_state(self) -> dict[str, int]:
        """How many frames ended in each state, in the order the states were first visited."""
        counts: dict[str, int] = {}
        for result in self.results:
            counts[result.state.value] = counts.get(result.state.value, 0) + 1
        return counts

    def states_visited(self) -> list[str]:
        """The state at the start, then every state entered (consecutive repeats collapsed)."""
        visited = [self.initial_state.value]
        for change in self.state_changes:
            if change.state.value != visited[-1]:
                visited.append(change.state.value)
        return visited

    def bad_frames_document(self) -> dict[str, Any]:
        """The bad frames for ``run.json``: policy, count, the first few with their errors."""
        return {
            "policy": self.bad_frame_policy.value,
            "count": len(self.bad_frames),
            "frames": [b.to_dict() for b in self.bad_frames[:_BAD_FRAMES_LISTED]],
        }

    def trajectory(self) -> Trajectory:
        """The valid poses (``T_world_cam``, world frame) with their frames' timestamps."""
        valid = [r for r in self.results if r.pose_valid and r.pose is not None]
        stamps = np.array([r.timestamp for r in valid], dtype=np.float64)
        poses = np.array([r.pose.T_world_cam for r in valid if r.pose is not None])
        return Trajectory(stamps, poses.reshape(-1, 4, 4))


FrameHook = Callable[[int, InputFrame, FrameResult], None]


def run_frames(
    tracker: Tracker,
    frames: Iterable[InputFrame],
    progress: ProgressDisplay | None = None,
    *,
    before_frame: Callable[[int, InputFrame], None] | None = None,
    after_frame: FrameHook | None = None,
    on_state_change: Callable[[StateChangeEvent], Any] | None = None,
    on_bad_frame: BadFramePolicy = BadFramePolicy.STOP,
) -> RunRecord:
    """Push ``frames`` into ``tracker``; ``before_frame``/``after_frame`` are the sink's hooks."""
    record = RunRecord(initial_state=tracker.state, bad_frame_policy=on_bad_frame)
    subscriptions = [
        tracker.events.on_state_change(record.state_changes.append),
        tracker.events.on_keyframe(record.keyframes.append),
    ]
    if on_state_change is not None:
        subscriptions.append(tracker.events.on_state_change(on_state_change))
    stop = _GracefulStop()
    start = time.perf_counter()
    try:
        for index, (frame, source_ms) in enumerate(_timed(frames)):
            record.add_sample("source", source_ms)
            if stop.requested:
                break
            if before_frame is not None and frame.error is None:
                before_frame(index, frame)
            result = _push(tracker, index, frame, record)
            if result is None:  # a bad frame, recorded: STOP made it the run's failure
                if record.failure is not None:
                    break
                continue
            _record_result(record, index, frame, result, after_frame)
            if progress is not None:
                progress.update(result, tracker.map_status.num_keyframes)
            if stop.requested:
                break
    except KeyboardInterrupt:  # a second Ctrl-C, or one outside a frame (e.g. in the source)
        record.interrupted = True
    except Exception as error:  # noqa: BLE001 - kept in the record, re-raised by the caller
        record.failure = error
    finally:
        stop.restore()
        if stop.requested:
            record.interrupted = True
            _log.warning("interrupted (Ctrl-C): keeping the frames tracked so far",
                         frames=record.num_frames)
        record.wall_seconds = time.perf_counter() - start
        for subscription in subscriptions:
            tracker.events.unregister(subscription)
    if not record.interrupted and record.failure is None:
        tracker.wait_for_map(timeout=None)  # an asynchronous rebuild still running belongs in the map
    record.num_keyframes = tracker.map_status.num_keyframes
    return record


def _push(
    tracker: Tracker, index: int, frame: InputFrame, record: RunRecord
) -> FrameResult | None:
    """The tracker's result for ``frame``, or None for a bad frame: recorded in ``record`` (and,
    under ``BadFramePolicy.STOP``, set as its failure); the tracker and its map are untouched."""
    try:
        if frame.error is not None:
            raise frame.error
        return tracker.push_frame(
            frame.image, timestamp=frame.timestamp, mask=frame.mask, bbox=frame.bbox,
            depth=frame.depth, depth_scale=frame.depth_scale,
        )  # fmt: skip
    except InputError as error:
        stamp = frame.timestamp if math.isfinite(frame.timestamp) else None
        record.bad_frames.append(BadFrame(index, stamp, str(error)))
        if record.bad_frame_policy is BadFramePolicy.STOP:
            record.failure = error
        else:
            _log.warning("bad frame skipped", position=index, error=str(error))
        return None


def _record_result(
    record: RunRecord,
    index: int,
    frame: InputFrame,
    result: FrameResult,
    after_frame: FrameHook | None,
) -> None:
    """Keep ``result`` and its stage timings; run the sink's hook, timed as stage ``sink``."""
    record.results.append(result)
    for stage, value in result.timings_ms.items():
        record.add_sample(stage, value)
    if after_frame is not None:
        sink_start = time.perf_counter()
        after_frame(index, frame, result)
        record.add_sample("sink", (time.perf_counter() - sink_start) * 1e3)


class _GracefulStop:
    """While the loop runs, the first SIGINT (Ctrl-C) only asks the loop to stop after the
    current frame; the default handler is back for a second one (stop at once).

    Python delivers signals to the main thread only; elsewhere (an app running the loop on a
    worker thread) nothing is installed and Ctrl-C keeps its default behaviour.
    """

    def __init__(self) -> None:
        self.requested = False
        self._installed = threading.current_thread() is threading.main_thread()
        self._previous: Any = signal.signal(signal.SIGINT, self._handle) if self._installed else None

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        # only a flag: printing from a signal handler could re-enter the console mid-write
        self.requested = True
        signal.signal(signal.SIGINT, signal.default_int_handler)

    def restore(self) -> None:
        if self._installed:  # None: a handler not set from Python; the default one stands in
            signal.signal(signal.SIGINT, self._previous or signal.default_int_handler)
            self._installed = False


def _timed(frames: Iterable[InputFrame]) -> Iterator[tuple[InputFrame, float]]:
    """Each frame with the milliseconds its source took to produce it."""
    iterator = iter(frames)
    while True:
        start = time.perf_counter()
        try:
            frame = next(iterator)
        except StopIteration:
            return
        yield frame, (time.perf_counter() - start) * 1e3

"""The frame loop shared by ``kvtracker track`` and ``kvtracker demo``, and what it records.

``run_frames`` pushes frames into a tracker, feeds the progress bar and the optional rerun sink,
and returns a :class:`RunRecord`: every frame result, every state change, and per-stage timings
(``source``: reading or rendering the frame; the tracker's own ``preprocess``/``track``/``map``;
``sink``: rerun logging). A Ctrl-C ends the loop cleanly: the record says ``interrupted`` and the
caller still writes the outputs of the frames processed.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from kvtracker_sdk.cli.progress import FrameProgress
from kvtracker_sdk.io.trajectory import Trajectory
from kvtracker_sdk.types import FrameResult, TrackingState

if TYPE_CHECKING:  # the tracker pulls in torch: imported by the commands when they run
    from kvtracker_sdk.tracking.events import KeyframeEvent, StateChangeEvent
    from kvtracker_sdk.tracking.tracker import Tracker

__all__ = ["InputFrame", "RunRecord", "StageStats", "run_frames"]


@dataclass(frozen=True)
class InputFrame:
    """One frame for the tracker: HxWx3 uint8 RGB, its time in seconds, optional mask or box."""

    image: np.ndarray
    timestamp: float
    mask: np.ndarray | None = None
    bbox: tuple[float, float, float, float] | None = None


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
    progress: FrameProgress,
    *,
    before_frame: Callable[[int, InputFrame], None] | None = None,
    after_frame: FrameHook | None = None,
    on_state_change: Callable[[StateChangeEvent], Any] | None = None,
) -> RunRecord:
    """Push ``frames`` into ``tracker``; ``before_frame``/``after_frame`` are the sink's hooks."""
    record = RunRecord(initial_state=tracker.state)
    subscriptions = [
        tracker.on_state_change(record.state_changes.append),
        tracker.on_keyframe(record.keyframes.append),
    ]
    if on_state_change is not None:
        subscriptions.append(tracker.on_state_change(on_state_change))
    start = time.perf_counter()
    try:
        for index, (frame, source_ms) in enumerate(_timed(frames)):
            record.add_sample("source", source_ms)
            if before_frame is not None:
                before_frame(index, frame)
            result = tracker.push_frame(
                frame.image, timestamp=frame.timestamp, mask=frame.mask, bbox=frame.bbox
            )
            record.results.append(result)
            for stage, value in result.timings_ms.items():
                record.add_sample(stage, value)
            if after_frame is not None:
                sink_start = time.perf_counter()
                after_frame(index, frame, result)
                record.add_sample("sink", (time.perf_counter() - sink_start) * 1e3)
            progress.update(result, tracker.map_status.num_keyframes)
    except KeyboardInterrupt:
        record.interrupted = True
    finally:
        record.wall_seconds = time.perf_counter() - start
        for subscription in subscriptions:
            tracker.unregister(subscription)
    if not record.interrupted:
        tracker.wait_for_map(timeout=None)  # an asynchronous rebuild still running belongs in the map
    return record


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

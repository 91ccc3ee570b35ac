"""Helpers for tracker tests: drive a Tracker with SimulatedBackend frames and record everything."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.geometry.sim3 import umeyama_alignment
from kvtracker_sdk.tracking.core.events import (
    KeyframeEvent,
    KeyframeRejectedEvent,
    MapUpdatedEvent,
    StateChangeEvent,
)
from kvtracker_sdk.tracking.facade.tracker import Tracker
from kvtracker_sdk.types import FrameResult, TrackingState

# Rendering at Pi3's model resolution of d = 224 for 4:3 frames (196 x 252) skips the resize, and
# flat (untextured) frames cost ~nothing: the whole 3,000-frame TUM run takes a few seconds.
SIZE = (196, 252)
WAIT_S = 120.0  # generous: a worker that never finishes fails the test instead of hanging it


def make_tracker(backend: SimulatedBackend, **config: Any) -> Tracker:
    return Tracker(TrackerConfig(resolution=224, **config), backend)


@dataclass
class Session:
    """Everything a tracker said while a simulated camera drove it."""

    results: list[FrameResult] = field(default_factory=list)
    truth: list[np.ndarray] = field(default_factory=list)  # ground-truth T_world_cam per result
    states: list[StateChangeEvent] = field(default_factory=list)
    keyframes: list[KeyframeEvent] = field(default_factory=list)
    rejected: list[KeyframeRejectedEvent] = field(default_factory=list)
    maps: list[MapUpdatedEvent] = field(default_factory=list)

    def listen(self, tracker: Tracker) -> Session:
        tracker.events.on_state_change(self.states.append)
        tracker.events.on_keyframe(self.keyframes.append)
        tracker.events.on_keyframe_rejected(self.rejected.append)
        tracker.events.on_map_updated(self.maps.append)
        return self

    def moves(self) -> list[tuple[str, str, str, int | None]]:
        return [
            (e.previous.value, e.state.value, e.reason.value, e.frame_index) for e in self.states
        ]

    def ate(self) -> float:
        """Translation RMSE of the valid poses after one Sim(3) alignment to the ground truth."""
        pairs = [
            (r.pose.translation, t[:3, 3])
            for r, t in zip(self.results, self.truth, strict=True)
            if r.pose_valid and r.pose is not None
        ]
        estimate = np.array([p for p, _ in pairs])
        truth = np.array([t for _, t in pairs])
        aligned = umeyama_alignment(estimate, truth).apply_to_points(estimate)
        return float(np.sqrt(np.mean(np.sum((aligned - truth) ** 2, axis=1))))


def drive(
    tracker: Tracker,
    backend: SimulatedBackend,
    *,
    start: int = 0,
    stop: int | None = None,
    session: Session | None = None,
    settle: bool = False,
    pace: bool = False,
    with_mask: bool = False,
) -> Session:
    """Push frames ``start:stop`` of the backend's trajectory.

    With asynchronous mapping, ``settle`` waits for every rebuild after each frame (maps swap at
    known frames). ``pace`` lets rebuilds run beside the frame loop but waits for the mapper where
    a slow worker would change the outcome: while the tracker is not TRACKING (the first map is
    building, so frames get no pose; or track is lost, and a timeout policy would discard the
    rebuild), when a keyframe candidate is waiting (a newer one would replace it) and at the end
    (a rebuild still running). The keyframes are then those of synchronous mapping, on any machine,
    at any load.
    """
    session = session if session is not None else Session().listen(tracker)
    for frame in backend.frames(SIZE, start=start, stop=stop, textured=False, with_mask=with_mask):
        result = tracker.push_frame(frame.image, timestamp=frame.timestamp, mask=frame.mask)
        session.results.append(result)
        session.truth.append(frame.T_world_cam)
        status = tracker.map_status
        waiting = (
            result.state is not TrackingState.TRACKING and status.rebuilding  # e.g. a timeout
            or status.keyframe_waiting  # policy would otherwise discard it: speed-dependent
        )
        if settle or (pace and waiting):
            assert tracker.wait_for_map(timeout=WAIT_S), "the mapping worker did not finish"
    if pace:  # a rebuild still running at the end belongs to the run (as in the CLI's loop)
        assert tracker.wait_for_map(timeout=WAIT_S), "the mapping worker did not finish"
    return session

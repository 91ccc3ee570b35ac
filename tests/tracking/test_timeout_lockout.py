"""A relocalisation timeout into a place where the network is steadily less confident.

The ``reset``/``new_map`` timeout policies start a new map only from a frame that reaches the lost
map's confidence floor (``confidence_threshold`` x its reference), so that no frame of the loss
becomes keyframe 0. In a place where the network is steadily less confident (0.3 here, 0.8 where
the lost map was made) every such frame used to be rejected for good. After ``FLOOR_RELAXES_AFTER``
rejected attempts the floor relaxes once, to ``confidence_threshold`` x the floor (docs/states.md):
poses come back within a stated number of frames, and frames of the loss are still never used.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from kvtracker_sdk.backends.base import TrackResult
from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import GroundTruth, decode_frame_index, orbit
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.tracking.mapping.map_keeper import FLOOR_RELAXES_AFTER
from kvtracker_sdk.types import HeadSet
from tests.tracking.sim_session import Session, drive, make_tracker

LOSS = (40, 120)  # the network is lost (confidence 0.1, garbage poses)
PLACE_CONFIDENCE = 0.3  # from the end of the loss on: right poses, steadily less confident
FRAMES = 200
THRESHOLD, TIMEOUT, RETRY = 0.5, 30, 15  # confidence_threshold; timeout_frames; retry_after_frames
TIMED_OUT_AT = LOSS[0] + 2 + TIMEOUT  # lost at the 3rd low frame, then TIMEOUT frames relocalising


class DimPlaceBackend(SimulatedBackend):
    """From frame ``dims_at`` on, the network tracks and maps correctly but is steadily less
    confident: every confidence is scaled by ``place_confidence / confidence``."""

    def __init__(self, truth: GroundTruth, *, dims_at: int, place_confidence: float,
                 **options: Any) -> None:
        super().__init__(truth, **options)
        self.dims_at, self.place_confidence = dims_at, place_confidence

    def _dimmed(self, frame: int) -> bool:
        lost = any(start <= frame < stop for start, stop in self.loss_segments)
        return frame >= self.dims_at and not lost

    def _map_confidence(self, frame: int) -> float:
        return self.place_confidence if self._dimmed(frame) else super()._map_confidence(frame)

    def track(
        self, image: np.ndarray, cache: KVCache, *, heads: HeadSet = HeadSet.CONFIDENCE
    ) -> TrackResult:
        result = super().track(image, cache, heads=heads)
        if not self._dimmed(decode_frame_index(image)) or result.confidence is None:
            return result
        factor = self.place_confidence / self.confidence
        assert result.confidence_map is not None
        return replace(result, confidence=result.confidence * factor,
                       confidence_map=result.confidence_map * np.float32(factor))


def _backend(loss_stop: int = LOSS[1]) -> DimPlaceBackend:
    return DimPlaceBackend(orbit(FRAMES), seed=5, loss_segments=[(LOSS[0], loss_stop)],
                           dims_at=loss_stop, place_confidence=PLACE_CONFIDENCE)


def _run(policy: str, backend: DimPlaceBackend, async_mapping: bool = False) -> Session:
    config = {
        "relocalization": {"lost_after": 3, "timeout_frames": TIMEOUT, "timeout_policy": policy,
                           "confidence_threshold": THRESHOLD},
        "rejection": {"retry_after_frames": RETRY},
        "threading": {"async_mapping": async_mapping},
    }
    with make_tracker(backend, **config) as tracker:
        return drive(tracker, backend, pace=True)


@pytest.mark.parametrize(
    ("policy", "async_mapping"), [("new_map", False), ("reset", False), ("new_map", True)]
)
def test_a_timeout_into_a_less_confident_place_gets_poses_back_within_the_bound(
    policy: str, async_mapping: bool
) -> None:
    session = _run(policy, _backend(), async_mapping)
    first_attempt = TIMED_OUT_AT + (1 if policy == "reset" else 0)  # reset: INIT, then a frame
    attempts = list(range(first_attempt, FRAMES, RETRY))
    # the bound (docs/states.md): the first attempt at or after both the relaxation and the loss
    bound = next(a for a in attempts[FLOOR_RELAXES_AFTER:] if a >= LOSS[1])
    after_loss = [r.frame_index for r in session.results[LOSS[0]:] if r.pose_valid]
    assert after_loss, "locked out: no pose after the loss"
    back = after_loss[0]
    # asynchronous mapping: the pass started at that frame is installed with the next one
    assert back == bound + async_mapping  # 132 (new_map) / 133 (reset), +1 asynchronous
    assert all(r.pose_valid for r in session.results[back:])  # like a fresh tracker (below)
    # the earlier guarantee: no pose from a frame of the loss, none of them is keyframe 0
    assert not any(r.pose_valid for r in session.results[LOSS[0]:LOSS[1]])
    assert [k.frame_index for k in session.keyframes if k.frame_index >= LOSS[0]][0] == bound
    # every attempt before it was rejected: strict floor first, then the relaxed one
    rejected = [e for e in session.rejected if e.frame_index >= LOSS[0]]
    assert [e.frame_index for e in rejected] == [a for a in attempts if a < bound]
    floor = rejected[0].reference_confidence
    strict, relaxed = rejected[:FLOOR_RELAXES_AFTER], rejected[FLOOR_RELAXES_AFTER:]
    assert all(e.reference_confidence == floor and e.ratio == 1.0 for e in strict)
    assert relaxed and all(
        e.reference_confidence == pytest.approx(THRESHOLD * floor, rel=1e-12) for e in relaxed
    )  # rel: one float multiplication
    # the app is told that the new map starts below the lost map's floor
    assert session.moves()[-1] == ("MAPPING", "TRACKING", "RELAXED_FLOOR", bound)


def test_a_loss_that_never_ends_still_gives_no_pose() -> None:
    """The relaxed floor still keeps every frame of the loss from becoming keyframe 0."""
    session = _run("new_map", _backend(loss_stop=FRAMES))
    assert not any(r.pose_valid for r in session.results[LOSS[0]:])
    rejected = [e.frame_index for e in session.rejected if e.frame_index >= LOSS[0]]
    assert rejected == list(range(TIMED_OUT_AT, FRAMES, RETRY))
    assert len(rejected) > FLOOR_RELAXES_AFTER  # relaxed attempts were made, and rejected


def test_a_fresh_tracker_tracks_the_less_confident_place_throughout() -> None:
    """The reference behaviour the relaxed floor gets back to: the place itself is trackable."""
    backend = _backend()
    with make_tracker(backend) as tracker:
        session = drive(tracker, backend, start=LOSS[1])
    assert all(r.pose_valid for r in session.results)
    assert session.moves()[-1] == ("MAPPING", "TRACKING", "BOOTSTRAP", 0)  # its own frame 0

"""The live intake: newest frame wins, drops are counted, the producer never waits on the worker.

A gated backend holds every network call until the test releases it, so which frame the worker
picks up is decided by events, not by timing.
"""

from __future__ import annotations

import queue
import threading

import numpy as np
import pytest

from kvtracker_sdk.backends.base import BackendInfo, MapResult, TrackResult
from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import decode_frame_index, orbit
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.errors import InputError, StateError
from kvtracker_sdk.tracking.facade.tracker import Tracker
from kvtracker_sdk.tracking.live.live_intake import LiveStats
from kvtracker_sdk.types import FrameResult, HeadSet

SIZE = (112, 140)
WAIT = 30.0  # generous: only a broken intake waits this long


class GatedBackend:
    """A SimulatedBackend whose map/track calls report the frame they got, then wait for a
    release."""

    def __init__(self, inner: SimulatedBackend) -> None:
        self.inner = inner
        self.entered: queue.Queue[int] = queue.Queue()
        self.release = threading.Semaphore(0)

    @property
    def info(self) -> BackendInfo:
        return self.inner.info

    def _gate(self, image: np.ndarray) -> None:
        self.entered.put(decode_frame_index(image))
        assert self.release.acquire(timeout=WAIT)

    def map(self, images: np.ndarray, masks: np.ndarray | None = None) -> MapResult:
        self._gate(images[-1])
        return self.inner.map(images, masks)

    def track(self, image: np.ndarray, cache: KVCache, *, heads: HeadSet = HeadSet.CONFIDENCE
              ) -> TrackResult:
        self._gate(image)
        return self.inner.track(image, cache, heads=heads)

    def close(self) -> None:
        self.inner.close()


def _balanced(stats: LiveStats) -> bool:
    return stats.submitted == stats.processed + stats.dropped + stats.pending + stats.in_progress


@pytest.fixture()
def gated() -> GatedBackend:
    return GatedBackend(SimulatedBackend(orbit(48), seed=4))


def test_the_worker_takes_the_newest_frame_and_counts_the_dropped(gated: GatedBackend) -> None:
    frames = list(gated.inner.frames(SIZE, stop=8))
    delivered: list[FrameResult] = []
    with Tracker(TrackerConfig(), gated) as tracker:
        tracker.events.on_result(delivered.append)
        assert tracker.live.latest() is None and tracker.live.stats == LiveStats.empty()
        tracker.submit(frames[0].image, timestamp=frames[0].timestamp)
        assert gated.entered.get(timeout=WAIT) == 0  # the worker is inside the mapping pass
        for frame in frames[1:4]:  # while it is busy: 1 and 2 are replaced, 3 waits
            tracker.submit(frame.image, timestamp=frame.timestamp)
        stats = tracker.live.stats
        assert (stats.submitted, stats.processed, stats.dropped, stats.pending) == (4, 0, 2, 1)
        assert stats.in_progress == 1 and _balanced(stats)

        gated.release.release()
        assert gated.entered.get(timeout=WAIT) == 3  # the newest available, not 1
        for frame in frames[4:7]:
            tracker.submit(frame.image, timestamp=frame.timestamp)
        assert _balanced(tracker.live.stats)
        gated.release.release()
        assert gated.entered.get(timeout=WAIT) == 6
        gated.release.release()
        assert tracker.live.wait_idle(timeout=WAIT)
        stats = tracker.live.stats
        latest = tracker.live.latest()
    assert (stats.submitted, stats.processed, stats.dropped, stats.pending) == (7, 3, 4, 0)
    assert stats.submitted == stats.processed + stats.dropped  # idle: nothing pending
    assert stats.failed == 0 and stats.delivered == 3 and stats.drop_rate == pytest.approx(4 / 7)
    assert [r.timestamp for r in delivered] == [frames[i].timestamp for i in (0, 3, 6)]
    assert latest is delivered[-1] and latest.pose_valid
    assert stats.latency_ms_p50 is not None and stats.latency_ms_p99 is not None
    assert 0 < stats.latency_ms_p50 <= stats.latency_ms_p95 <= stats.latency_ms_p99  # type: ignore[operator]
    assert gated.entered.empty()


def test_bad_frames_are_reported_not_raised_and_the_intake_closes(gated: GatedBackend) -> None:
    errors: list[BaseException] = []
    frame = next(iter(gated.inner.frames(SIZE, stop=1)))
    tracker = Tracker(TrackerConfig(), gated)
    tracker.events.on_frame_error(errors.append)
    tracker.submit(np.zeros((4, 4), np.uint8))  # not an RGB image: the worker refuses it
    assert tracker.live.wait_idle(timeout=WAIT)
    assert len(errors) == 1 and isinstance(errors[0], InputError)
    stats = tracker.live.stats
    assert (stats.submitted, stats.processed, stats.failed, stats.delivered) == (1, 1, 1, 0)

    tracker.submit(frame.image)  # enters the mapping pass and waits there
    assert gated.entered.get(timeout=WAIT) == 0
    tracker.submit(frame.image)  # pending while the tracker closes: dropped
    closer = threading.Thread(target=tracker.close)
    closer.start()
    gated.release.release()
    closer.join(WAIT)
    assert not closer.is_alive()
    stats = tracker.live.stats
    assert (stats.submitted, stats.processed, stats.dropped, stats.pending) == (3, 2, 1, 0)
    with pytest.raises(StateError):
        tracker.submit(frame.image)


def test_the_producer_never_takes_the_trackers_lock(gated: GatedBackend) -> None:
    """While the worker holds the tracker (inside the network), submit still returns: it runs
    to completion on this thread with the worker blocked."""
    frames = list(gated.inner.frames(SIZE, stop=40))
    with Tracker(TrackerConfig(), gated) as tracker:
        # one clock for the whole session: stamps that go backwards are refused
        tracker.submit(frames[0].image, timestamp=frames[0].timestamp)
        assert gated.entered.get(timeout=WAIT) == 0
        for frame in frames[1:]:
            tracker.submit(frame.image, timestamp=frame.timestamp)  # would deadlock if it waited
        assert tracker.live.stats.dropped == len(frames) - 2
        gated.release.release()
        assert gated.entered.get(timeout=WAIT) == len(frames) - 1
        gated.release.release()
        assert tracker.live.wait_idle(timeout=WAIT)


def test_live_callbacks_are_subscriptions_on_the_trackers_one_callback_system() -> None:
    """``on_result`` / ``on_frame_error`` return a ``Subscription`` like every ``on_*`` callback,
    and ``unregister`` removes them; a raising callback does not stop the intake."""
    backend = SimulatedBackend(orbit(8), seed=4)
    frames = list(backend.frames(SIZE, stop=3))
    results: list[FrameResult] = []
    errors: list[BaseException] = []

    def broken(_: FrameResult) -> None:
        raise RuntimeError("an app's bug")

    with Tracker(TrackerConfig(), backend) as tracker:
        handle = tracker.events.on_result(results.append)
        tracker.events.on_result(broken)
        tracker.events.on_frame_error(errors.append)
        tracker.submit(frames[0].image, timestamp=frames[0].timestamp)
        assert tracker.live.wait_idle(timeout=WAIT)
        tracker.submit(np.zeros((4, 4), np.uint8))
        assert tracker.live.wait_idle(timeout=WAIT)
        assert tracker.events.unregister(handle) and not tracker.events.unregister(handle)
        tracker.submit(frames[1].image, timestamp=frames[1].timestamp)
        assert tracker.live.wait_idle(timeout=WAIT)
        assert [r.frame_index for r in results] == [0]  # not the one after unregister
        assert len(errors) == 1 and isinstance(errors[0], InputError)
        assert tracker.live.stats.processed == 3

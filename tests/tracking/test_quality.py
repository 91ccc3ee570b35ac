"""ConfidenceMonitor: relative threshold, loss / recovery / timeout streaks."""

from __future__ import annotations

import numpy as np

from kvtracker_sdk.tracking.core.quality import ConfidenceMonitor, frame_confidence, masked_mean


def _monitor(timeout: int | None = 5) -> ConfidenceMonitor:
    monitor = ConfidenceMonitor(
        threshold=0.5, lost_after=3, recover_after=2, timeout_frames=timeout
    )
    monitor.set_reference(0.8)  # confident at >= 0.4
    return monitor


def test_threshold_is_relative_to_the_reference() -> None:
    monitor = _monitor()
    assert monitor.is_confident(0.4)
    assert not monitor.is_confident(0.39)
    monitor.set_reference(0.2)
    assert monitor.is_confident(0.1)
    assert monitor.is_confident(None)  # no confidence head: no loss detection


def test_lost_after_exactly_lost_after_low_frames() -> None:
    monitor = _monitor()
    verdicts = [monitor.update(0.1, relocalizing=False) for _ in range(3)]
    assert [v.lost for v in verdicts] == [False, False, True]
    assert not any(v.confident for v in verdicts)


def test_a_confident_frame_breaks_the_low_streak() -> None:
    monitor = _monitor()
    monitor.update(0.1, relocalizing=False)
    monitor.update(0.1, relocalizing=False)
    monitor.update(0.9, relocalizing=False)
    assert not monitor.update(0.1, relocalizing=False).lost


def test_recovered_after_recover_after_confident_frames() -> None:
    monitor = _monitor()
    verdicts = [monitor.update(0.8, relocalizing=True) for _ in range(2)]
    assert [v.recovered for v in verdicts] == [False, True]


def test_timeout_counts_relocalizing_frames_only() -> None:
    monitor = _monitor(timeout=4)
    results = [monitor.update(0.1, relocalizing=True).timed_out for _ in range(4)]
    assert results == [False, False, False, True]
    assert not monitor.update(0.1, relocalizing=False).timed_out  # counter restarts
    never = _monitor(timeout=None)
    assert not any(never.update(0.1, relocalizing=True).timed_out for _ in range(100))


def test_reset_clears_every_streak() -> None:
    monitor = _monitor()
    monitor.update(0.1, relocalizing=True)
    monitor.update(0.1, relocalizing=True)
    monitor.reset()
    assert (monitor.low_streak, monitor.high_streak, monitor.relocalizing_frames) == (0, 0, 0)


def test_frame_confidence_uses_the_mask_when_there_is_one() -> None:
    confidence_map = np.zeros((4, 4), dtype=np.float32)
    confidence_map[:2] = 1.0
    mask = np.zeros((4, 4), dtype=bool)
    mask[0] = True
    assert frame_confidence(0.5, confidence_map, mask) == 1.0
    assert frame_confidence(0.5, confidence_map, None) == 0.5
    assert frame_confidence(None, None, mask) is None
    assert masked_mean(confidence_map, None) == 0.5

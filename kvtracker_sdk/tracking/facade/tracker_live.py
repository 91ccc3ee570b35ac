"""``tracker.live``: the reading side of the live intake (``tracker.submit`` feeds it).

A thin view over the tracker's ``LiveIntake`` (``live/live_intake.py``), which the first
``submit`` creates: it owns no state and no lock, and reads the intake at each call, so a view
taken before the first ``submit`` sees it too. Before that, ``latest()`` is None, ``stats`` all
zero and ``wait_idle()`` True at once.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from kvtracker_sdk.tracking.live.live_intake import LiveStats
from kvtracker_sdk.types import FrameResult

if TYPE_CHECKING:  # pragma: no cover
    from kvtracker_sdk.tracking.facade.tracker import Tracker

__all__ = ["TrackerLive"]


class TrackerLive:
    """The live intake's results, counters and idle wait (``tracker.live``)."""

    __slots__ = ("_tracker",)

    def __init__(self, tracker: Tracker) -> None:
        self._tracker = tracker

    def latest(self) -> FrameResult | None:
        """The live worker's most recent result (None before the first)."""
        intake = self._tracker._intake
        return None if intake is None else intake.latest()

    @property
    def stats(self) -> LiveStats:
        """Live intake counters: submitted, processed, dropped, delivered FPS, latency."""
        intake = self._tracker._intake
        return LiveStats.empty() if intake is None else intake.stats

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Wait until the live worker has no frame pending or in progress; True if so within
        ``timeout`` seconds (None: however long it takes)."""
        intake = self._tracker._intake
        return True if intake is None else intake.wait_idle(timeout)

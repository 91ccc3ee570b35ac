"""Non-blocking intake for a live camera: hand a frame over and return at once.

A camera thread cannot wait for a network step (tens of milliseconds to seconds, depending on the
model and the machine). ``LiveIntake`` gives it
``submit(image, timestamp)``, which only stores the frame in a **one-slot mailbox** and returns
(no lock the worker ever holds, no network, no I/O; a copy of the image unless ``copy=False``):
the mailbox is a ``deque(maxlen=1)`` and the worker's doorbell a ``queue.SimpleQueue``, both
single C calls under the GIL, so a worker descheduled by a busy machine cannot hold the camera
thread up (a ``threading.Condition`` shared with the worker did; the handover's measured cost
beside a bare image copy: ``benchmarks/README.md``, ``live.py``). One worker
thread takes whatever the slot holds — always the newest frame — and runs ``Tracker.push_frame``
on it. A frame still waiting when a newer one arrives is dropped and counted (the official
KV-Tracker demo reads its RealSense through a one-slot queue the same way).

Accounting: ``submitted == processed + dropped + pending + in_progress`` at every moment (the last
two are 0 or 1; once idle, ``submitted == processed + dropped``); ``processed`` counts frames the
worker finished, including those ``push_frame`` refused
(``failed``, reported to ``on_error``). Results reach the app through ``on_result`` callbacks (on
the worker thread) and the ``latest()`` snapshot. ``stats`` adds the delivered FPS (results in the
last two seconds) and capture-to-result latency percentiles over the last 1,000 results, measured
from ``captured_at`` (a ``time.perf_counter()`` reading taken when the frame was captured; the
moment of ``submit`` if not given).

Rebuilds: with ``threading.async_mapping`` (what ``kvtracker track`` uses for live sources) a
rebuild runs on the mapping worker and tracking continues against the old map; with synchronous
mapping the keyframe's ``push_frame`` runs the mapping pass on the intake worker, and frames
arriving meanwhile are dropped — the producer is never blocked either way.
"""

from __future__ import annotations

import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from kvtracker_sdk.errors import KVTrackerError, StateError
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.tracking.core.events import EventBus, EventKind, Subscription
from kvtracker_sdk.types import FrameResult

__all__ = ["LiveIntake", "LiveStats"]

_log = get_logger(__name__)
_LATENCY_SAMPLES = 1000
_FPS_WINDOW_S = 2.0

ResultCallback = Callable[[FrameResult], Any]
ErrorCallback = Callable[[BaseException], Any]


@dataclass(frozen=True)
class LiveStats:
    """A snapshot of a live intake's counters (see the module docstring)."""

    submitted: int
    processed: int  # finished by the worker (delivered + failed)
    dropped: int  # replaced by a newer frame before the worker took them
    pending: int  # 0 or 1: waiting in the slot
    in_progress: int  # 0 or 1: being tracked by the worker
    failed: int  # push_frame raised (bad input, a closed tracker, ...)
    delivered_fps: float  # results per second over the last two seconds
    latency_ms_p50: float | None  # capture -> result available, last 1,000 results
    latency_ms_p95: float | None
    latency_ms_p99: float | None

    @classmethod
    def empty(cls) -> LiveStats:
        return cls(0, 0, 0, 0, 0, 0, 0.0, None, None, None)

    @property
    def delivered(self) -> int:
        return self.processed - self.failed

    @property
    def drop_rate(self) -> float:
        """Dropped / submitted (0 before the first frame)."""
        return self.dropped / self.submitted if self.submitted else 0.0


@dataclass(frozen=True)
class _Pending:
    image: Any
    timestamp: float
    mask: Any
    bbox: Any
    camera: Camera | None
    captured_at: float
    color: str = "rgb"
    depth: Any = None  # the frame's registered depth image (Tracker.push_frame's)
    depth_scale: Any = None
    gravity: Any = None


class LiveIntake:
    """A one-slot, newest-frame-wins intake in front of ``tracker`` (a worker thread)."""

    def __init__(
        self, push_frame: Callable[..., FrameResult], *, events: EventBus | None = None,
        copy: bool = True,
    ) -> None:
        """An adapter over a tracker: ``push_frame`` is its ``Tracker.push_frame`` (the intake
        needs nothing else of it); ``events``: the bus its ``on_result`` / ``on_error``
        callbacks are registered on (the tracker's, so that ``tracker.events.on_result``
        and ``unregister`` reach them)."""
        self._push_frame = push_frame
        self._events = events if events is not None else EventBus()
        self._copy = bool(copy)
        self._mailbox: deque[_Pending] = deque(maxlen=1)  # append drops the waiting frame
        self._doorbell: queue.SimpleQueue[None] = queue.SimpleQueue()
        self._cond = threading.Condition(threading.Lock())  # worker and app side only
        self._busy = False
        self._closing = False
        self._submitted = 0  # written by the producer only
        self._taken = self._processed = self._failed = 0  # written by the worker only
        self._latencies: deque[float] = deque(maxlen=_LATENCY_SAMPLES)
        self._delivered_at: deque[float] = deque()
        self._latest: FrameResult | None = None
        self._worker = threading.Thread(target=self._run, name="kvtracker-live", daemon=True)
        self._worker.start()

    # ------------------------------------------------------------------ producer side
    def submit(
        self,
        image: np.ndarray,
        timestamp: float | None = None,
        *,
        mask: np.ndarray | None = None,
        bbox: Any = None,
        camera: Camera | None = None,
        captured_at: float | None = None,
        color: str = "rgb",
        depth: np.ndarray | None = None,
        depth_scale: float | None = None,
        gravity: Any = None,
    ) -> None:
        """Hand ``image`` over and return at once (a frame still waiting is dropped).

        ``timestamp``: the capture time in seconds (default: ``time.time()`` now), reported in
        the result. ``captured_at``: the capture moment on ``time.perf_counter()``'s clock, for
        the latency statistics (default: now). ``depth``/``depth_scale``/``gravity`` travel with
        the frame (dropped with it). The frame is validated by the worker; a bad one goes to
        ``on_error``. StateError after ``close()``.
        """
        now = time.perf_counter()
        if self._copy and isinstance(image, np.ndarray):
            image = image.copy()  # the camera may reuse its buffer
        if self._copy and isinstance(depth, np.ndarray):
            depth = depth.copy()
        item = _Pending(
            image, time.time() if timestamp is None else timestamp, mask, bbox, camera,
            now if captured_at is None else captured_at, color, depth, depth_scale, gravity,
        )
        if self._closing:
            raise StateError("the live intake is closed")
        self._submitted += 1
        self._mailbox.append(item)  # atomic; replaces (drops) a frame still waiting
        self._doorbell.put(None)  # never blocks

    # ------------------------------------------------------------------ app side
    def on_result(self, callback: ResultCallback) -> Subscription:
        """Call ``callback(result)`` on the worker thread after every processed frame."""
        return self._events.register(EventKind.RESULT, callback)

    def on_error(self, callback: ErrorCallback) -> Subscription:
        """Call ``callback(exception)`` on the worker thread when ``push_frame`` raises."""
        return self._events.register(EventKind.FRAME_ERROR, callback)

    def latest(self) -> FrameResult | None:
        """The most recent result (None before the first)."""
        return self._latest

    @property
    def stats(self) -> LiveStats:
        with self._cond:
            latencies = np.array(self._latencies, dtype=np.float64)
            now = time.perf_counter()
            recent = [t for t in self._delivered_at if now - t <= _FPS_WINDOW_S]
            # a snapshot taken while the producer submits may be off by one for an instant
            submitted, pending = self._submitted, len(self._mailbox)
            dropped = max(submitted - self._taken - pending, 0)
            counts = (submitted, self._processed, dropped, pending, int(self._busy), self._failed)
        fps = len(recent) / _FPS_WINDOW_S if recent else 0.0
        if len(recent) >= 2 and now - recent[0] < _FPS_WINDOW_S:  # younger than the window
            fps = (len(recent) - 1) / max(recent[-1] - recent[0], 1e-9)
        p50, p95, p99 = (
            (None, None, None) if latencies.size == 0
            else (float(v) for v in np.percentile(latencies, [50, 95, 99]))
        )
        return LiveStats(*counts, delivered_fps=fps, latency_ms_p50=p50,
                         latency_ms_p95=p95, latency_ms_p99=p99)

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Wait until no frame is pending or being processed; True if so within ``timeout``."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._mailbox and not self._busy, timeout)

    def close(self, *, drain: bool = True, timeout: float | None = None) -> None:
        """Stop taking frames; ``drain`` processes a pending frame first (else it is dropped).
        Waits for the worker (at most ``timeout`` s). Idempotent."""
        if not drain:
            self._mailbox.clear()  # counted as dropped: submitted but never taken
        self._closing = True
        self._doorbell.put(None)
        with self._cond:
            self._cond.notify_all()
        if self._worker is not threading.current_thread():
            self._worker.join(timeout)

    # ------------------------------------------------------------------ worker
    def _run(self) -> None:
        while True:
            if self._closing and not self._mailbox:
                with self._cond:
                    self._cond.notify_all()  # wake wait_idle
                return
            self._doorbell.get()
            while True:  # one wake-up serves every bell rung so far
                try:
                    self._doorbell.get_nowait()
                except queue.Empty:
                    break
            with self._cond:
                try:
                    item = self._mailbox.popleft()
                except IndexError:  # already taken after an earlier bell
                    continue
                self._taken += 1
                self._busy = True
            result, error = self._process(item)
            done = time.perf_counter()
            with self._cond:
                self._processed += 1
                self._busy = False
                if error is not None:
                    self._failed += 1
                else:
                    self._latest = result
                    self._latencies.append((done - item.captured_at) * 1e3)
                    self._delivered_at.append(done)
                    while self._delivered_at and done - self._delivered_at[0] > _FPS_WINDOW_S:
                        self._delivered_at.popleft()
                self._cond.notify_all()
            self._deliver(result, error)

    def _process(self, item: _Pending) -> tuple[FrameResult | None, BaseException | None]:
        try:
            result = self._push_frame(
                item.image, timestamp=item.timestamp, mask=item.mask, bbox=item.bbox,
                camera=item.camera, color=item.color, depth=item.depth,
                depth_scale=item.depth_scale, gravity=item.gravity,
            )
        except KVTrackerError as exc:
            return None, exc
        except Exception as exc:  # a bug must not kill the worker silently: log, report, go on
            _log.exception("live_frame_failed", error=repr(exc))
            return None, exc
        return result, None

    def _deliver(self, result: FrameResult | None, error: BaseException | None) -> None:
        # a raising callback is logged by the bus: an app's callback must not stop the intake
        if error is None:
            self._events.emit(EventKind.RESULT, result)
        else:
            self._events.emit(EventKind.FRAME_ERROR, error)

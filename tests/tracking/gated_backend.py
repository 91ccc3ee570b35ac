"""A SimulatedBackend whose mapping passes the test holds and releases: the test, not the machine's
speed, decides when a rebuild on the mapping worker finishes."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from kvtracker_sdk.backends.base import MapResult
from kvtracker_sdk.backends.simulated import SimulatedBackend

# Generous: a gate that is never opened fails the test with a message instead of hanging CI.
GATE_TIMEOUT_S = 120.0


class GatedBackend(SimulatedBackend):
    """``hold(n)`` makes mapping pass ``n`` (1-based) wait until ``release(n)``.

    ``started(n)`` waits until pass ``n`` has begun (on whichever thread runs it); passes that are
    not held run at once.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._lock = threading.Lock()
        self._gates: dict[int, threading.Event] = {}
        self._started: dict[int, threading.Event] = {}
        self.passes = 0

    def _event(self, table: dict[int, threading.Event], n: int) -> threading.Event:
        with self._lock:
            return table.setdefault(n, threading.Event())

    def hold(self, n: int) -> None:
        self._event(self._gates, n)

    def release(self, n: int) -> None:
        self._event(self._gates, n).set()

    def started(self, n: int, timeout: float = GATE_TIMEOUT_S) -> bool:
        return self._event(self._started, n).wait(timeout)

    def map(self, images: np.ndarray, masks: np.ndarray | None = None) -> MapResult:
        with self._lock:
            self.passes += 1
            n = self.passes
            gate = self._gates.get(n)
        self._event(self._started, n).set()
        if gate is not None and not gate.wait(GATE_TIMEOUT_S):
            raise AssertionError(f"mapping pass {n} was held and never released")
        return super().map(images, masks)

"""CPU thread settings that do not fall over when the cores are busy (layer 0: no torch here,
so that ``kvtracker_sdk/__init__.py`` can set the wait policy before torch loads).

Two OpenMP threads on a 2-core CPU that other processes also use ran a tracking step 2-5x slower
than one thread: at every parallel region the threads wait for each other, and with libgomp's
default (active) wait policy a waiting thread spins for a while, taking the core the late thread
needs. So:

- ``import kvtracker_sdk`` sets ``OMP_WAIT_POLICY=PASSIVE`` (waiting threads sleep) unless the
  variable is set or torch was imported first (OpenMP reads it once, when torch loads);
  ``wait_policy()`` reports what torch's OpenMP runs with.
- ``choose_threads`` picks the intra-op thread count: with passive waiting, every core this
  process may run on (``os.sched_getaffinity``): a sleeping waiter costs nothing, and a process
  with more runnable threads gets a larger share of a busy CPU (measured under a load average of
  7 on 2 cores, DA3-Small: 2 passive threads 0.26 s median, 1 thread 0.62 s, 2 spinning threads
  3.98 s; ``benchmarks/thread_defaults.py``). With spinning waiters (torch was imported before
  ``kvtracker_sdk``, or the policy was set active), only the cores other processes leave free
  (1-minute load average), at least 1. Never more than torch is already set to
  (``OMP_NUM_THREADS`` or a caller's ``torch.set_num_threads`` stay upper bounds).
  ``TorchBackend(threads=None)`` applies it; an ``int`` overrides it.

``torch.set_num_threads`` is process-wide: the last backend made (or the caller) sets it.
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass

from kvtracker_sdk.errors import ConfigError

__all__ = [
    "ThreadSettings",
    "choose_threads",
    "prefer_passive_wait",
    "usable_cores",
    "wait_policy",
]

# what ``prefer_passive_wait`` found when the package was imported (None: not called yet)
_WAIT_POLICY_AT_IMPORT: str | None = None


def prefer_passive_wait() -> None:
    """Set ``OMP_WAIT_POLICY=PASSIVE`` if nobody chose a policy and OpenMP has not started yet
    (torch not imported). Called once by ``kvtracker_sdk/__init__.py``; imports nothing heavy."""
    global _WAIT_POLICY_AT_IMPORT
    if "OMP_WAIT_POLICY" not in os.environ and "torch" not in sys.modules:
        os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    _WAIT_POLICY_AT_IMPORT = _policy_in_effect(torch_loaded="torch" in sys.modules)


def _policy_in_effect(*, torch_loaded: bool) -> str:
    if torch_loaded and _WAIT_POLICY_AT_IMPORT is not None:
        return _WAIT_POLICY_AT_IMPORT
    value = os.environ.get("OMP_WAIT_POLICY")
    if value is None:
        return "active (OpenMP default: waiting threads spin)"
    return value.lower()


def wait_policy() -> str:
    """The OpenMP wait policy torch's threads run with: ``passive``, ``active`` or the default.

    Read from ``OMP_WAIT_POLICY`` as it was when torch was (or will be) loaded; a change of the
    variable after that has no effect, so it is not reported.
    """
    return _policy_in_effect(torch_loaded="torch" in sys.modules)


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity; the CPU count where that is unknown)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # macOS / Windows have no sched_getaffinity
        return max(1, os.cpu_count() or 1)


def choose_threads(cores: int, load_average: float, *, passive: bool) -> int:
    """Intra-op threads for ``cores`` usable cores when other processes keep ``load_average``
    cores busy. ``passive`` waiting: all ``cores``. Spinning: the free cores (rounded to the
    nearest whole core), at least 1 — e.g. 2 cores: load 0.3 -> 2 threads, load 0.8 -> 1, load
    4 -> 1 (a spinning thread that waits for a descheduled sibling takes the core it needs).
    """
    if cores < 1:
        raise ConfigError(f"cores must be >= 1, got {cores}")
    if passive or not math.isfinite(load_average) or load_average < 0:
        return cores
    free = math.floor(cores - load_average + 0.5)
    return max(1, min(cores, free))


@dataclass(frozen=True)
class ThreadSettings:
    """The thread settings a backend runs with (``TorchBackend.threads``)."""

    threads: int  # torch intra-op threads set by the backend
    source: str  # "auto" (choose_threads) or "user" (the ``threads`` argument)
    usable_cores: int  # len(os.sched_getaffinity(0))
    load_average: float | None  # 1-minute load average when chosen (None: unavailable)
    wait_policy: str  # OpenMP wait policy in effect (``wait_policy()``)

    @classmethod
    def resolve(cls, requested: int | None, current: int) -> ThreadSettings:
        """``requested`` threads (``ConfigError`` below 1), or for None the automatic choice,
        at most ``current`` (torch's thread count now)."""
        cores = usable_cores()
        try:
            load: float | None = os.getloadavg()[0]
        except (AttributeError, OSError):  # Windows
            load = None
        if requested is None:
            passive = wait_policy() == "passive"
            chosen = choose_threads(cores, 0.0 if load is None else load, passive=passive)
            threads, source = max(1, min(chosen, current)), "auto"
        elif isinstance(requested, bool) or not isinstance(requested, int) or requested < 1:
            raise ConfigError(f"threads must be an int >= 1 or None (automatic), got {requested!r}")
        else:
            threads, source = requested, "user"
        return cls(threads, source, cores, load, wait_policy())

    def describe(self) -> str:
        """One line for logs and ``BackendInfo.accelerations``, e.g. ``threads=1 (auto, ...)``."""
        load = "?" if self.load_average is None else f"{self.load_average:.1f}"
        return (
            f"threads={self.threads} ({self.source}; {self.usable_cores} cores, load {load}, "
            f"omp-wait {self.wait_policy.split(' ')[0]})"
        )

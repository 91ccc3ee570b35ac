"""CPU thread settings that do not fall over when the cores are busy (layer 0: no torch here,
so that ``kvtracker_sdk/__init__.py`` can set the wait policy before torch loads).

Two OpenMP threads on a 2-core CPU that other processes also use run a tracking step several
times slower than one thread: at every parallel region the threads wait for each other, and with
libgomp's default (active) wait policy a waiting thread spins for a while, taking the core the
late thread needs. So:

- ``import kvtracker_sdk`` sets ``OMP_WAIT_POLICY=PASSIVE`` (waiting threads sleep) unless the
  variable is set or torch was imported first; ``wait_policy()`` reports what torch's OpenMP
  runs with. libgomp (torch's OpenMP on Linux) reads the variable once, in its load-time
  constructor, i.e. when torch is imported (``OMP_DISPLAY_ENV=TRUE`` prints it then), and has
  no call to change it later: an app that imports torch first keeps the spinning default.
- So the backends check when they are built (``ThreadSettings.resolve``): with the spinning
  default that nobody chose (``spins_by_default``), automatic threads are 1 (no OpenMP team, so
  no thread ever waits: the passive policy's effect) and a warning names the fix; an explicit
  ``threads`` above 1 is refused with ``ConfigError`` naming the fix (``SPINNING_FIX``). An
  explicit ``OMP_WAIT_POLICY=ACTIVE`` is a choice and is honoured.
- ``choose_threads`` picks the intra-op thread count: with passive waiting, every core this
  process may run on (``os.sched_getaffinity``): a sleeping waiter costs nothing, and a process
  with more runnable threads gets a larger share of a busy CPU (``benchmarks/thread_defaults.py``;
  figures: ``benchmarks/README.md#figures-behind-the-code``). With spinning waiters (torch was
  imported before ``kvtracker_sdk``, or the policy was set active), only the cores other
  processes leave free (1-minute load average), at least 1. Never more than torch is already set
  to (``OMP_NUM_THREADS`` or a caller's ``torch.set_num_threads`` stay upper bounds).
  ``TorchBackend(threads=None)`` applies it; an ``int`` overrides it.

``torch.set_num_threads`` is process-wide: the last backend made (or the caller) sets it.
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass

from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.log import get_logger

__all__ = [
    "SPINNING_FIX",
    "ThreadSettings",
    "choose_threads",
    "prefer_passive_wait",
    "spins_by_default",
    "usable_cores",
    "wait_policy",
]

_log = get_logger(__name__)
_DEFAULT_POLICY = "active (OpenMP default: waiting threads spin)"
SPINNING_FIX = (
    "torch was imported before kvtracker_sdk with OMP_WAIT_POLICY unset, so its OpenMP threads "
    "spin while they wait (OpenMP read the variable when torch loaded; it cannot be changed "
    "now), and more than one thread makes every step many times slower whenever another "
    "process uses the CPU. Fix: import kvtracker_sdk before torch, or start the process with "
    "OMP_WAIT_POLICY=PASSIVE in its environment (e.g. `OMP_WAIT_POLICY=PASSIVE python app.py`), "
    "or use threads=1; set OMP_WAIT_POLICY=ACTIVE before start to keep spinning threads on "
    "purpose"
)

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
        return _DEFAULT_POLICY
    return value.lower()


def wait_policy() -> str:
    """The OpenMP wait policy torch's threads run with: ``passive``, ``active`` or the default.

    Read from ``OMP_WAIT_POLICY`` as it was when torch was (or will be) loaded; a change of the
    variable after that has no effect, so it is not reported.
    """
    return _policy_in_effect(torch_loaded="torch" in sys.modules)


def spins_by_default() -> bool:
    """True when torch's OpenMP runs with the spinning default that nobody chose: torch was loaded
    before ``kvtracker_sdk`` could set ``OMP_WAIT_POLICY=PASSIVE`` and the variable was unset."""
    return "torch" in sys.modules and wait_policy() == _DEFAULT_POLICY


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
        at most ``current`` (torch's thread count now). With the unchosen spinning policy
        (``spins_by_default``) the automatic choice is 1 thread (warning logged) and a request
        above 1 is a ``ConfigError`` naming the fix."""
        cores = usable_cores()
        try:
            load: float | None = os.getloadavg()[0]
        except (AttributeError, OSError):  # Windows
            load = None
        spinning = spins_by_default()
        if requested is None and spinning:
            _log.warning("one torch thread: OpenMP spins", fix=SPINNING_FIX)
            threads, source = 1, "auto"
        elif requested is None:
            passive = wait_policy() == "passive"
            chosen = choose_threads(cores, 0.0 if load is None else load, passive=passive)
            threads, source = max(1, min(chosen, current)), "auto"
        elif isinstance(requested, bool) or not isinstance(requested, int) or requested < 1:
            raise ConfigError(f"threads must be an int >= 1 or None (automatic), got {requested!r}")
        elif spinning and requested > 1:
            raise ConfigError(f"threads={requested} refused: {SPINNING_FIX}")
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

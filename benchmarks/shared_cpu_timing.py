"""Timing on a shared CPU: how much of the machine other processes used while we measured.

``time_once`` (``tracking_vs_recompute``) gives wall and process CPU time of a call. On a CPU
shared with other jobs neither is trustworthy alone: with torch's default thread count, a busy
core makes OpenMP threads wait for each other at every barrier and a step can take 10-20x its
quiet time. So every round of calls also records the cores *other* processes used meanwhile —
the machine's busy time (``/proc/stat``) minus this process's CPU time, over the round's wall
time — and samples from rounds where that exceeds what the run leaves free are set aside.

A point's samples are ``{"wall": [...], "cpu": [...], "others": [...]}`` (seconds, seconds,
cores), one entry per timed round.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from benchmarks.tracking_vs_recompute import time_once

__all__ = [
    "OtherLoad",
    "best",
    "busy_seconds",
    "measure_rounds",
    "new_samples",
    "wait_for_quiet",
]

Samples = dict[str, list[float]]


def busy_seconds() -> float:
    """CPU seconds all processes have used since boot (Linux ``/proc/stat``; nan elsewhere)."""
    stat = Path("/proc/stat")
    if not stat.exists():
        return float("nan")
    user, nice, system, _idle, _iowait, irq, softirq, steal = stat.read_text().split()[1:9]
    ticks = sum(int(v) for v in (user, nice, system, irq, softirq, steal))
    return ticks / os.sysconf("SC_CLK_TCK")


class OtherLoad:
    """Cores used by other processes since construction: (all busy time - ours) / wall."""

    def __init__(self) -> None:
        self.busy, self.cpu, self.wall = busy_seconds(), time.process_time(), time.perf_counter()

    def cores(self) -> float:
        wall = time.perf_counter() - self.wall
        others = busy_seconds() - self.busy - (time.process_time() - self.cpu)
        return max(0.0, others / wall)


def wait_for_quiet(limit: float, max_wait: float) -> float:
    """Sleep in 2 s windows until other processes use <= ``limit`` cores or ``max_wait`` s pass;
    returns the last reading (cores)."""
    deadline = time.monotonic() + max_wait
    while True:
        window = OtherLoad()
        time.sleep(2.0 if max_wait > 0 else 0.2)
        cores = window.cores()
        if not cores > limit or time.monotonic() >= deadline:  # nan (no /proc/stat): go
            return cores


def new_samples() -> Samples:
    """Empty samples of one point."""
    return {"wall": [], "cpu": [], "others": []}


def _record(samples: Samples, wall: float, cpu: float, others: float) -> None:
    samples["wall"].append(wall)
    samples["cpu"].append(cpu)
    samples["others"].append(others)


def measure_rounds(
    calls: Sequence[tuple[Samples, Callable[[], object]]],
    allowed: float,
    *,
    repeats: int,
    warmup: int,
    budget: float,
    max_wait: float,
) -> None:
    """Time each call once per round into its samples, with the cores others used during the
    round. Round-robin, so a busy spell hits all calls alike; after a contended round (others >
    ``allowed`` cores) wait for quiet, ``max_wait`` s in all. Stops when every call has
    ``repeats`` clean samples, after ``warmup + 3 * repeats`` rounds, or once the timed rounds
    (waits excluded) took ``budget`` seconds."""
    spent, rounds, wait_until = 0.0, 0, time.monotonic() + max_wait
    while True:
        load, timed = OtherLoad(), [(samples, *time_once(call)) for samples, call in calls]
        others = load.cores()
        spent += sum(wall for _, wall, _ in timed)
        rounds += 1
        if rounds > warmup:
            for samples, wall, cpu in timed:
                _record(samples, wall, cpu, others)
            clean = min(sum(not o > allowed for o in s["others"]) for s, _, _ in timed)
            if clean >= repeats or rounds >= warmup + 3 * repeats or spent > budget:
                return
        if others > allowed:
            wait_for_quiet(allowed, max(0.0, wait_until - time.monotonic()))


def best(samples: Samples | None, clock: str, allowed: float) -> tuple[float, bool] | None:
    """(minimum on ``clock`` over clean samples, True), else (over all samples, False); None
    when the point was not timed."""
    if not samples or not samples[clock]:
        return None
    clean = [t for t, o in zip(samples[clock], samples["others"], strict=True) if not o > allowed]
    return (min(clean), True) if clean else (min(samples[clock]), False)

"""Tests of ``benchmarks/shared_cpu_timing.py``: contention readings and clean-sample minima."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from benchmarks.shared_cpu_timing import OtherLoad, best, measure_rounds, new_samples


def test_best_prefers_clean_samples() -> None:
    samples = {"wall": [0.5, 0.2, 0.3], "cpu": [0.4, 0.2, 0.3], "others": [0.1, 1.5, 0.05]}
    assert best(samples, "wall", allowed=1.0) == (0.3, True)  # 0.2 was contended
    assert best(samples, "cpu", allowed=0.0) == (0.2, False)  # none clean: over all
    assert best(None, "wall", allowed=1.0) is None
    assert best(new_samples(), "wall", allowed=1.0) is None


def test_other_load_is_a_core_count() -> None:
    if not Path("/proc/stat").exists():
        pytest.skip("no /proc/stat: contention is not measured on this system")
    load = OtherLoad()
    deadline = time.process_time() + 0.3
    while time.process_time() < deadline:  # busy ourselves: our own CPU time is not "others"
        pass
    # units are cores: at most every CPU busy (+ one 10 ms tick of /proc/stat rounding per CPU)
    cpus = os.cpu_count() or 1
    assert 0.0 <= load.cores() <= cpus * (1 + 0.01 / 0.3) + 1e-9


def test_measure_rounds_stops_at_clean_repeats() -> None:
    calls = {"a": 0, "b": 0}
    points = [(new_samples(), lambda k=k: calls.__setitem__(k, calls[k] + 1)) for k in calls]
    # every round is clean with 1000 cores allowed: warmup + repeats rounds, round-robin
    measure_rounds(points, 1000.0, repeats=3, warmup=1, budget=60.0, max_wait=0.0)
    assert calls == {"a": 4, "b": 4}
    for samples, _ in points:
        assert {key: len(values) for key, values in samples.items()} == {
            "wall": 3, "cpu": 3, "others": 3,
        }  # fmt: skip


def test_measure_rounds_gives_up_when_never_clean() -> None:
    samples = new_samples()
    # no round can be clean (allowed < 0): 3 * repeats timed rounds after the warmup, no more
    measure_rounds([(samples, lambda: None)], -1.0, repeats=2, warmup=1, budget=60.0, max_wait=0.0)
    assert len(samples["wall"]) == 6
    assert best(samples, "wall", allowed=-1.0) == (min(samples["wall"]), False)

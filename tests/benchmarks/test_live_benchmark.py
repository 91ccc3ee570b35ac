"""Smoke test of ``benchmarks/live.py``: a short simulated run whose counts add up (no timing
checks: the speed targets are measured by the benchmark itself)."""

from __future__ import annotations

from benchmarks.live import _table, run_live, sim_case
from tests.helpers import shared_path


def test_a_short_live_run_accounts_for_every_frame() -> None:
    shared_path("data", "tum_fr2_desk", "groundtruth.txt")  # skips without ../shared
    make, frames = sim_case(40, step_s=0.002)
    with make() as tracker:
        row = run_live(tracker, frames[:40], rate_hz=400.0, count=40)
    assert row["submitted"] == row["processed"] + row["dropped"] == 40
    assert row["failed"] == 0 and row["processed"] >= 1
    assert 0 <= row["drop_rate"] < 1 and row["handover_ms"]["max"] >= row["handover_ms"]["p50"]
    latency = row["latency_ms"]
    assert 0 < latency["p50"] <= latency["p95"] <= latency["p99"]
    row["case"] = "smoke"
    assert "| smoke | 400 Hz × 40 |" in _table([row])

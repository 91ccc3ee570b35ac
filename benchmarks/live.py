"""A live camera loop: a producer thread submits frames at 30 or 60 Hz, ``Tracker.submit`` hands
them to the live worker (newest frame wins), rebuilds run on the mapping worker.

Cases (``--cases``):

* ``sim``: the simulated backend with a fixed 50 ms tracking step (``FixedStepBackend`` sleeps
  the rest of the step, as a GPU call releases the GIL) and a mapping pass of 50 ms per
  keyframe; frames rendered at 120x160, a keyframe every 20 processed frames (rebuilds about
  every second), at most 16 keyframes.
* ``da3``: DA3-Small, random weights, bf16 on the CPU (``--threads``), on the 20 real TUM fr2
  frames of ``../shared/data/tum_fr2_desk`` (cycled), resolution 224, a keyframe every 10
  processed frames, at most 8.

Reported per case and rate: delivered FPS (results / run time), drop rate (dropped /
submitted), capture-to-result latency p50/p95/p99 over all results (``captured_at`` is taken
just before ``submit``), the producer's handover time (``submit`` call: max and p99.9; beside
it, as a reference, the same thread timing a bare copy of the image: what the machine and the
GIL alone cost a few lines of Python on this thread), FPS
while a rebuild runs vs between rebuilds (each result's interval to the previous result counted
in the state the result reports, ``extras["rebuilding"]``), rebuilds accepted, and the first
map's cost (first submit to the first result with a pose). Every run checks that
``submitted == processed + dropped`` once the worker is idle.

    python -m benchmarks.live --cases sim da3 --rates 30 60 --frames 3000 --da3-frames 600
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: no spin-waiting on a shared CPU

import numpy as np  # noqa: E402

from kvtracker_sdk.backends.base import BackendInfo, MapResult, TrackResult  # noqa: E402
from kvtracker_sdk.backends.simulated import SimulatedBackend  # noqa: E402
from kvtracker_sdk.cache.kv_cache import KVCache  # noqa: E402
from kvtracker_sdk.config import TrackerConfig  # noqa: E402
from kvtracker_sdk.tracking.facade.tracker import Tracker  # noqa: E402
from kvtracker_sdk.types import FrameResult, HeadSet  # noqa: E402

RESULTS = Path(__file__).parent / "results"
SHARED = Path(__file__).resolve().parents[2] / "shared"


class FixedStepBackend:
    """``inner`` with every tracking step taking ``step_s`` and mapping ``step_s`` per keyframe
    (the remainder is slept: the GIL is free, as during a real network call)."""

    def __init__(self, inner: SimulatedBackend, step_s: float) -> None:
        self.inner, self.step_s = inner, step_s

    @property
    def info(self) -> BackendInfo:
        return self.inner.info

    def map(self, images: np.ndarray, masks: np.ndarray | None = None) -> MapResult:
        start = time.perf_counter()
        result = self.inner.map(images, masks)
        _sleep_until(start + self.step_s * len(images))
        return result

    def track(self, image: np.ndarray, cache: KVCache, *, heads: HeadSet = HeadSet.CONFIDENCE
              ) -> TrackResult:
        start = time.perf_counter()
        result = self.inner.track(image, cache, heads=heads)
        _sleep_until(start + self.step_s)
        return result

    def close(self) -> None:
        self.inner.close()


def _sleep_until(deadline: float) -> None:
    remaining = deadline - time.perf_counter()
    if remaining > 0:
        time.sleep(remaining)


def run_live(
    tracker: Tracker, frames: Sequence[np.ndarray], rate_hz: float, count: int
) -> dict[str, Any]:
    """The producer loop on this thread; returns the measurements (see the module docstring)."""
    captured: dict[float, float] = {}
    records: list[tuple[float, float, bool, bool]] = []  # (done, latency s, rebuilding, pose)
    lock = threading.Lock()
    overheads: list[float] = []  # push_frame time beyond the backend's step (ms)
    outcomes: list[tuple[bool, bool]] = []  # (the network tracked it, the pose is valid)

    def on_result(result: FrameResult) -> None:
        done = time.perf_counter()
        assert result.timestamp is not None
        latency = done - captured[result.timestamp]
        with lock:
            records.append((done, latency, bool(result.extras.get("rebuilding")),
                            result.pose is not None))
            overheads.append(result.timings_ms.get("total", 0.0) - result.timings_ms.get("track", 0.0))
            outcomes.append(("track" in result.timings_ms, result.pose_valid))

    tracker.events.on_result(on_result)
    states: set[Any] = set()
    tracker.events.on_state_change(lambda event: states.add(event.state))
    blocks, copies = np.empty(count), np.empty(count)
    period = 1.0 / rate_hz
    start = time.perf_counter()
    for k in range(count):
        _sleep_until(start + k * period)
        stamp = float(k)
        t0 = time.perf_counter()
        captured[stamp] = t0  # before submit: the worker may finish the frame at once
        tracker.submit(frames[k % len(frames)], timestamp=stamp, captured_at=t0)
        blocks[k] = time.perf_counter() - t0  # the handover alone (a dict store besides)
        t1 = time.perf_counter()  # reference: the same image copy without any intake
        frames[k % len(frames)].copy()
        copies[k] = time.perf_counter() - t1
    produced = time.perf_counter()
    assert tracker.live.wait_idle(timeout=600)
    tracker.wait_for_map(timeout=600)
    stats = tracker.live.stats
    assert stats.submitted == stats.processed + stats.dropped == count, stats
    with lock:
        done = np.array([r[0] for r in records])
        latency_ms = np.array([r[1] for r in records]) * 1e3
        rebuilding = np.array([r[2] for r in records])
        first_pose = next((r[0] for r in records if r[3]), float("nan"))
    gaps = np.diff(np.concatenate(([start], done)))
    during, between = gaps[rebuilding], gaps[~rebuilding]
    return {
        "rate_hz": rate_hz,
        "submitted": stats.submitted,
        "processed": stats.processed,
        "dropped": stats.dropped,
        "failed": stats.failed,
        "seconds": produced - start,
        "delivered_fps": len(records) / (produced - start),
        "drop_rate": stats.drop_rate,
        "latency_ms": {p: float(np.percentile(latency_ms, q))
                       for p, q in (("p50", 50), ("p95", 95), ("p99", 99))},
        "handover_ms": {"max": float(blocks.max() * 1e3),
                        "p99.9": float(np.percentile(blocks, 99.9) * 1e3),
                        "p50": float(np.median(blocks) * 1e3)},
        "reference_copy_ms": {"max": float(copies.max() * 1e3),
                              "p99.9": float(np.percentile(copies, 99.9) * 1e3)},
        "fps_during_rebuild": float(len(during) / during.sum()) if len(during) else None,
        "fps_between_rebuilds": float(len(between) / between.sum()) if len(between) else None,
        "frames_during_rebuild": int(len(during)),
        "rebuilds": tracker.map_status.generation,
        "keyframes": tracker.map_status.num_keyframes,
        "first_map_s": first_pose - start,
        "tracked_fraction": float(np.mean([o[0] for o in outcomes])),
        "valid_pose_fraction": float(np.mean([o[1] for o in outcomes])),
        "states_visited": sorted({s.value for s in states}),
        "tracker_overhead_ms": {"p50": float(np.percentile(overheads, 50)),
                                "p95": float(np.percentile(overheads, 95)),
                                "max": float(np.max(overheads))},
    }


def sim_case(count: int, step_s: float) -> tuple[Callable[[], Tracker], list[np.ndarray]]:
    gt = SHARED / "data" / "tum_fr2_desk" / "groundtruth.txt"
    size = (120, 160)
    inner = SimulatedBackend.from_tum(gt, camera_size=size, seed=0)
    frames = [f.image for f in inner.frames(size, stop=min(count, 600))]
    config = TrackerConfig.from_dict({
        "resolution": 224, "threading": {"async_mapping": True},
        "keyframing": {"interval_frames": 20, "budget": {"max_keyframes": 16}},
    })
    return (lambda: Tracker(config, FixedStepBackend(inner, step_s))), frames


def da3_case(threads: int) -> tuple[Callable[[], Tracker], list[np.ndarray]]:
    import cv2
    import torch

    from kvtracker_sdk.backends.torch_backend import TorchBackend
    from kvtracker_sdk.models.da3 import DA3Config, DepthAnything3

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    files = sorted((SHARED / "data" / "tum_fr2_desk" / "rgb").glob("*.png"))
    frames = [cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB) for f in files]
    backend = TorchBackend(DepthAnything3(DA3Config.small()), dtype=torch.bfloat16,
                           model_name="da3-small")
    config = TrackerConfig.from_dict({
        "resolution": 224, "threading": {"async_mapping": True},
        "keyframing": {"interval_frames": 10, "budget": {"max_keyframes": 8}},
    })
    return (lambda: Tracker(config, backend)), frames


def _table(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| case | producer | delivered FPS | drop rate | latency p50 / p95 / p99 (ms) | "
        "handover max / p99.9 (ms) | FPS during / between rebuilds | rebuilds | first map (s) | "
        "valid poses |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lat, hand = r["latency_ms"], r["handover_ms"]
        during = "—" if r["fps_during_rebuild"] is None else f"{r['fps_during_rebuild']:.1f}"
        between = "—" if r["fps_between_rebuilds"] is None else f"{r['fps_between_rebuilds']:.1f}"
        lines.append(
            f"| {r['case']} | {r['rate_hz']:.0f} Hz × {r['submitted']} | {r['delivered_fps']:.1f} | "
            f"{r['drop_rate']:.1%} | {lat['p50']:.0f} / {lat['p95']:.0f} / {lat['p99']:.0f} | "
            f"{hand['max']:.2f} / {hand['p99.9']:.3f} | {during} / {between} | {r['rebuilds']} | "
            f"{r['first_map_s']:.2f} | {r['valid_pose_fraction']:.0%} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", nargs="+", default=["sim", "da3"], choices=["sim", "da3"])
    parser.add_argument("--rates", nargs="+", type=float, default=[30.0, 60.0])
    parser.add_argument("--frames", type=int, default=3000, help="frames per sim run")
    parser.add_argument("--da3-frames", type=int, default=600, help="frames per DA3 run")
    parser.add_argument("--step-ms", type=float, default=50.0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--name", default="live")
    parser.add_argument(
        "--switch-interval-ms", type=float, default=None,
        help="CPython's GIL switch interval for this run (default: the interpreter's, 5 ms): a "
        "thread that wants the GIL waits up to this long while the worker runs Python code, so "
        "an app that needs a shorter handover tail lowers it (sys.setswitchinterval)")
    args = parser.parse_args(argv)
    if args.switch_interval_ms is not None:
        sys.setswitchinterval(args.switch_interval_ms / 1e3)
    rows: list[dict[str, Any]] = []
    load_before = os.getloadavg()
    for case in args.cases:
        if case == "sim":
            make, frames = sim_case(args.frames, args.step_ms / 1e3)
            count, label = args.frames, f"simulated, {args.step_ms:.0f} ms step"
        else:
            make, frames = da3_case(args.threads)
            count, label = args.da3_frames, f"DA3-Small bf16, {args.threads} threads"
        for rate in args.rates:
            with make() as tracker:
                row = run_live(tracker, frames, rate, count)
            row["case"] = label
            rows.append(row)
            print(_table([row]).splitlines()[-1], flush=True)
    load_after = os.getloadavg()
    print()
    print(_table(rows))
    print(f"\nload average before {load_before[0]:.2f}, after {load_after[0]:.2f} "
          f"({os.cpu_count()} CPUs)")
    RESULTS.mkdir(exist_ok=True)
    out = RESULTS / f"{args.name}.json"
    out.write_text(json.dumps({
        "rows": rows, "args": vars(args), "load_average": [load_before, load_after],
        "switch_interval_s": sys.getswitchinterval(),
        "cpus": os.cpu_count(), "machine": platform.processor() or platform.machine(),
    }, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

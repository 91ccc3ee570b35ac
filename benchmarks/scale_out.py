"""Sequences per minute of ``eval-many`` on 1, 2 and 4 workers: local process pool vs Ray.

    python -m benchmarks.scale_out --sequences 8 --frames 300 --workers 1 2 4

Every run evaluates the same manifest of simulated sequences (no weights: the simulated backend
costs ~1 ms a frame, so the table shows the engines' own overheads — worker start-up, task
shipping, result gathering — more than tracking). Engines alternate (serial, then local and Ray
per worker count) in one run; the machine's load average is recorded with the table. On a
2-core machine more than 2 workers oversubscribe the CPU: the 4-worker rows show that cost.

How it maps to a GPU cluster: a worker (pool process or Ray actor) loads the model once and runs
whole sequences, so with real weights a sequence is seconds to minutes of GPU work and the
per-task overhead measured here (tens of ms) is noise; give each actor one GPU
(``num_gpus=1`` in ``ray_runtime.actor_class``) and as many actors as GPUs, and point
``ensure_ray`` at the cluster (``ray.init(address=...)`` before calling ``run_many``).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

from kvtracker_sdk.scale.manifest import EvalManifest
from kvtracker_sdk.scale.runner import run_many

RESULTS = Path(__file__).resolve().parent / "results"


def manifest(sequences: int, frames: int) -> EvalManifest:
    return EvalManifest.model_validate({
        "configs": {"default": {"resolution": 224}},
        "sequences": [
            {"name": f"orbit{k}", "simulated": {"orbit_frames": frames, "seed": k,
                                                "orbit_turns": 0.5 + 0.1 * k}}
            for k in range(sequences)
        ],
    })


def timed(plan: EvalManifest, engine: str, workers: int) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        result = run_many(plan, out, engine=engine, workers=workers)
        seconds = time.perf_counter() - start
    return {"engine": engine, "workers": workers, "seconds": seconds,
            "sequences_per_minute": 60.0 * len(result.results) / seconds,
            "metrics": result.metrics()}


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequences", type=int, default=8)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--json", type=Path, default=RESULTS / "scale_out.json")
    args = parser.parse_args(argv)
    plan = manifest(args.sequences, args.frames)
    load_before = os.getloadavg()
    rows = [timed(plan, "serial", 1)]
    for workers in args.workers:
        rows.append(timed(plan, "local", workers))
        rows.append(timed(plan, "ray", workers))  # the first Ray row includes starting Ray
    load_after = os.getloadavg()
    reference = rows[0]["metrics"]
    print(f"{args.sequences} simulated sequences x {args.frames} frames; "
          f"load average {load_before[0]:.2f} before, {load_after[0]:.2f} after; {os.cpu_count()} cores")
    print("| engine | workers | seconds | sequences/min | same numbers as serial |")
    print("|---|---|---|---|---|")
    for row in rows:
        same = row["metrics"] == reference
        print(f"| {row['engine']} | {row['workers']} | {row['seconds']:.1f} | "
              f"{row['sequences_per_minute']:.1f} | {'yes' if same else 'NO'} |")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({
        "sequences": args.sequences, "frames": args.frames, "cores": os.cpu_count(),
        "load_average_before": load_before, "load_average_after": load_after,
        "rows": [{k: v for k, v in row.items() if k != "metrics"}
                 | {"same_numbers_as_serial": row["metrics"] == reference} for row in rows],
    }, indent=2))
    return rows


if __name__ == "__main__":
    main()

"""Thread settings on a busy CPU: OpenMP wait policy x intra-op threads, and the automatic choice.

One worker process per setting (``OMP_WAIT_POLICY`` must be set before torch loads): ``active``
and ``passive`` wait policies with 1 and ``--max-threads`` threads, plus ``auto`` (what
``TorchBackend(threads=None)`` picks after ``import kvtracker_sdk``, which makes the policy
passive). Each builds the same model (``--model``, bf16, random weights) and a random cache of
``--keyframes`` keyframes at ``--size``; the parent asks the workers in turn, round by round
(rotating order), for one tracking step (camera head), so all see the same load. Wall time is
what a user waits for: the table gives the median and best wall time per setting and the median
relative to one passive thread, with the load average.

    python -m benchmarks.thread_defaults --rounds 15

Writes ``benchmarks/results/<--name>.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).parent / "results"
ROOT = Path(__file__).resolve().parent.parent


def _worker(args: argparse.Namespace) -> None:
    """Build the model and cache; answer each ``step`` line with ``{"wall": s}``."""
    import kvtracker_sdk

    assert kvtracker_sdk  # a statement between: import sorting must not move torch above it
    import torch

    from benchmarks.model_families import build_model, random_cache
    from kvtracker_sdk.models.registry import family_of
    from kvtracker_sdk.threads import ThreadSettings, wait_policy
    from kvtracker_sdk.types import HeadSet

    requested = None if args.worker_threads == 0 else args.worker_threads
    settings = ThreadSettings.resolve(requested, torch.get_num_threads())
    torch.set_num_threads(settings.threads)
    model = build_model(args.model, torch.bfloat16)
    layout = family_of(model).cache_layout(model)
    tokens = model.tokens_per_frame(args.size, args.size)
    cache = random_cache(layout, model.compute_dtype, args.keyframes, tokens)
    query = torch.rand(1, 3, args.size, args.size, generator=torch.Generator().manual_seed(0))
    print(json.dumps({"threads": settings.threads, "wait_policy": wait_policy()}), flush=True)
    with torch.no_grad():
        for line in sys.stdin:
            if line.strip() != "step":
                break
            start = time.perf_counter()
            model.forward_track(query, cache, heads=HeadSet.CAMERA)
            print(json.dumps({"wall": time.perf_counter() - start}), flush=True)


class Worker:
    def __init__(self, policy: str | None, threads: int, args: argparse.Namespace) -> None:
        env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
        env["PYTHONPATH"] = str(ROOT)
        if policy is not None:
            env["OMP_WAIT_POLICY"] = policy
        command = [sys.executable, "-m", "benchmarks.thread_defaults", "--worker-threads",
                   str(threads), "--model", args.model, "--size", str(args.size),
                   "--keyframes", str(args.keyframes)]  # fmt: skip
        self.process = subprocess.Popen(command, env=env, cwd=ROOT, stdin=subprocess.PIPE,
                                        stdout=subprocess.PIPE, text=True)  # fmt: skip
        self.info = self._read()

    def _read(self) -> dict[str, Any]:
        assert self.process.stdout is not None
        line = self.process.stdout.readline()
        if not line:
            raise RuntimeError(f"worker exited with {self.process.wait()}")
        return dict(json.loads(line))

    def step(self) -> float:
        assert self.process.stdin is not None
        self.process.stdin.write("step\n")
        self.process.stdin.flush()
        return float(self._read()["wall"])

    def close(self) -> None:
        assert self.process.stdin is not None
        self.process.stdin.close()
        self.process.wait(timeout=60)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worker-threads", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--model", default="da3-small")
    parser.add_argument("--size", type=int, default=224)
    parser.add_argument("--keyframes", type=int, default=8)
    parser.add_argument("--max-threads", type=int, default=os.cpu_count() or 2)
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--name", default="thread_defaults")
    args = parser.parse_args(argv)
    if args.worker_threads is not None:
        _worker(args)
        return {}
    top = args.max_threads
    settings = {"active, 1 thread": ("ACTIVE", 1), f"active, {top} threads": ("ACTIVE", top),
                "passive, 1 thread": ("PASSIVE", 1), f"passive, {top} threads": ("PASSIVE", top),
                "auto (SDK default)": (None, 0)}  # fmt: skip
    workers = {name: Worker(policy, threads, args) for name, (policy, threads) in settings.items()}
    samples: dict[str, list[float]] = {name: [] for name in workers}
    load_start = os.getloadavg()
    try:
        names = list(workers)
        for name in names:  # warm-up
            workers[name].step()
        for round_index in range(args.rounds):
            shift = round_index % len(names)
            for name in names[shift:] + names[:shift]:
                samples[name].append(workers[name].step())
    finally:
        for worker in workers.values():
            worker.close()
    load_end = os.getloadavg()
    base = statistics.median(samples["passive, 1 thread"])
    rows = {name: {"threads": workers[name].info["threads"],
                   "wait_policy": workers[name].info["wait_policy"],
                   "median_wall_s": statistics.median(s), "best_wall_s": min(s),
                   "median_vs_passive_1": statistics.median(s) / base, "samples": s}
            for name, s in samples.items()}  # fmt: skip
    result = {"model": args.model, "size": args.size, "keyframes": args.keyframes,
              "cpus": os.cpu_count(), "rounds": args.rounds, "rows": rows,
              "load_average_start": load_start, "load_average_end": load_end}  # fmt: skip
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{args.name}.json").write_text(json.dumps(result, indent=1) + "\n")
    print("| setting | threads | wait policy | median wall (s) | best wall (s) | median / passive 1 |")
    print("|---|---:|---|---:|---:|---:|")
    for name, row in rows.items():
        print(f"| {name} | {row['threads']} | {row['wait_policy'].split()[0]} "
              f"| {row['median_wall_s']:.3f} | {row['best_wall_s']:.3f} "
              f"| {row['median_vs_passive_1']:.2f} |")  # fmt: skip
    print(f"load average {load_start[0]:.1f} -> {load_end[0]:.1f}")
    return result


if __name__ == "__main__":
    main()

"""bf16 tracking step of this checkout against another checkout of the SDK, interleaved.

Compares the bf16 precision scheme of two code trees (e.g. this one, with an fp32 residual stream,
and a ``git worktree`` of an older commit whose residual stream was bf16) on the same machine at
the same time: one worker process per tree (``PYTHONPATH`` = that tree) builds the model with the
same seed, a random K/V cache of N keyframes and a query frame, then the parent asks the workers in
turn, round by round (alternating which goes first), for one timed ``forward_track`` step (camera
head). Both trees therefore see the same load; the ratio of their best (minimum) times is what the
table reports, with the load average. Workers use ``--threads`` torch threads (default 1: on a CPU
shared with other jobs one thread's process CPU time repeats within a few per cent).

Run from the repository root::

    git worktree add /tmp/kvt-old <commit>
    python -m benchmarks.bf16_step --old /tmp/kvt-old --models pi3-large da3-small

Writes ``benchmarks/results/<--name>.json`` (default ``bf16_step``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).parent / "results"
ROOT = Path(__file__).resolve().parent.parent


# ---------------------------------------------------------------------------- worker side
def _worker(model_name: str, size: tuple[int, int], keyframes: int, threads: int) -> None:
    """Build the model in bf16 and a cache, then answer each ``step`` line on stdin with
    ``{"wall": s, "cpu": s}`` on stdout. Uses only APIs every SDK version has."""
    import torch

    from kvtracker_sdk.cache import KVCache
    from kvtracker_sdk.models.da3 import DA3Config, DepthAnything3
    from kvtracker_sdk.models.pi3 import Pi3, Pi3Config
    from kvtracker_sdk.types import HeadSet

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    factories = {
        "pi3-large": lambda: Pi3(Pi3Config.large()),
        "da3-small": lambda: DepthAnything3(DA3Config.small()),
        "da3-base": lambda: DepthAnything3(DA3Config.base()),
    }
    model: Any = factories[model_name]().eval().requires_grad_(False)
    model.set_precision(torch.bfloat16)
    height, width = size
    layout, tokens = _cache_layout(model), model.tokens_per_frame(height, width)
    shape = (1, layout.num_heads, keyframes * tokens, layout.head_dim)
    block = torch.randn(shape, generator=torch.Generator().manual_seed(keyframes))
    layers = [block.to(model.compute_dtype)] * layout.num_layers
    cache = KVCache.from_layers(
        layers, layers, layout=layout, tokens_per_frame=tokens, keyframe_ids=range(keyframes)
    )
    query = torch.rand(1, 3, height, width, generator=torch.Generator().manual_seed(0))
    print(json.dumps({"ready": True, "cache_dtype": str(cache.dtype)}), flush=True)
    with torch.no_grad():
        for line in sys.stdin:
            if line.strip() != "step":
                break
            wall, cpu = time.perf_counter(), time.process_time()
            model.forward_track(query, cache, heads=HeadSet.CAMERA)
            print(
                json.dumps({"wall": time.perf_counter() - wall, "cpu": time.process_time() - cpu}),
                flush=True,
            )


def _cache_layout(model: Any) -> Any:
    """The model's cache layout in either tree: the family registry (current) or the older
    per-family adapters."""
    try:
        from kvtracker_sdk.models.registry import family_of
    except ImportError:  # a tree before the family records
        from kvtracker_sdk.backends.torch_families import family_adapter  # type: ignore[import-not-found]

        return family_adapter(model).layout
    return family_of(model).cache_layout(model)


# ---------------------------------------------------------------------------- parent side
class Worker:
    """One worker process running ``tree``'s SDK."""

    def __init__(self, tree: Path, args: argparse.Namespace, model_name: str) -> None:
        env = {**os.environ, "PYTHONPATH": str(tree), "OMP_WAIT_POLICY": "PASSIVE"}
        command = [
            sys.executable, str(Path(__file__).resolve()), "--worker", model_name,
            "--size", str(args.size[0]), str(args.size[1]),
            "--keyframes", str(args.keyframes), "--threads", str(args.threads),
        ]  # fmt: skip
        self.process = subprocess.Popen(
            command, env=env, cwd=tree, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )
        self.info = self._read()

    def _read(self) -> dict[str, Any]:
        assert self.process.stdout is not None
        line = self.process.stdout.readline()
        if not line:
            raise RuntimeError(f"worker exited with {self.process.wait()}")
        return dict(json.loads(line))

    def step(self) -> dict[str, float]:
        assert self.process.stdin is not None
        self.process.stdin.write("step\n")
        self.process.stdin.flush()
        return {k: float(v) for k, v in self._read().items()}

    def close(self) -> None:
        assert self.process.stdin is not None
        self.process.stdin.close()
        self.process.wait(timeout=60)


def compare(model_name: str, args: argparse.Namespace) -> dict[str, Any]:
    """Interleaved rounds of one step per tree; samples per tree and the load averages."""
    trees = {"new": ROOT, "old": Path(args.old).resolve()}
    samples: dict[str, dict[str, list[float]]] = {k: {"wall": [], "cpu": []} for k in trees}
    workers = {}
    try:
        for key, tree in trees.items():  # built one after the other: peak memory of one build
            workers[key] = Worker(tree, args, model_name)
        load_start = os.getloadavg()
        for round_index in range(args.warmup + args.rounds):
            order = list(trees) if round_index % 2 == 0 else list(reversed(trees))
            for key in order:
                timing = workers[key].step()
                if round_index >= args.warmup:
                    for clock in ("wall", "cpu"):
                        samples[key][clock].append(timing[clock])
        load_end = os.getloadavg()
    finally:
        for worker in workers.values():
            worker.close()
    best = {key: {clock: min(v) for clock, v in s.items()} for key, s in samples.items()}
    return {
        "model": model_name,
        "size": list(args.size),
        "keyframes": args.keyframes,
        "cache_dtype": {key: w.info["cache_dtype"] for key, w in workers.items()},
        "samples": samples,
        "best": best,
        "ratio_new_over_old": {c: best["new"][c] / best["old"][c] for c in ("wall", "cpu")},
        "loadavg_start": load_start,
        "loadavg_end": load_end,
    }


def markdown_table(rows: list[dict[str, Any]], clock: str) -> str:
    lines = [
        f"| model | H×W | N | old bf16 step (s, {clock}) | new bf16 step (s) | new / old "
        "| load avg (1 min, start → end) |",
        "|---|---|---:|---:|---:|---:|---|",
    ]
    for row in rows:
        height, width = row["size"]
        lines.append(
            f"| {row['model']} | {height}×{width} | {row['keyframes']} "
            f"| {row['best']['old'][clock]:.3f} | {row['best']['new'][clock]:.3f} "
            f"| {row['ratio_new_over_old'][clock]:.3f} "
            f"| {row['loadavg_start'][0]:.2f} → {row['loadavg_end'][0]:.2f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--old", help="root of the other SDK checkout (e.g. a git worktree)")
    parser.add_argument("--models", nargs="+", default=["pi3-large", "da3-small"])
    parser.add_argument("--size", nargs=2, type=int, default=[224, 224], metavar=("H", "W"))
    parser.add_argument("--keyframes", type=int, default=8)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=8)
    parser.add_argument("--clock", choices=("wall", "cpu"), default="cpu")
    parser.add_argument("--name", default="bf16_step")
    args = parser.parse_args(argv)
    if args.worker:
        _worker(args.worker, tuple(args.size), args.keyframes, args.threads)
        return
    if not args.old:
        parser.error("--old is required")
    rows = [compare(name, args) for name in args.models]
    result = {
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "threads": args.threads,
        "rows": rows,
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{args.name}.json").write_text(json.dumps(result, indent=1))
    print(markdown_table(rows, args.clock))


if __name__ == "__main__":
    main()

"""How fast a tracking step could be on this CPU at best: a roofline bound on the speed-up over the
official cached step, for Pi3 (whose FLOPs ``benchmarks/flops.py`` counts).

The SDK computes the same transformer as the official code, so its step cannot take less time
than its matrix products at the machine's best bf16 matrix-product rate. This script:

1. counts the step's FLOPs (``flops.tracking_step_flops``) for the heads the tracker reads
   (``HeadSet.CONFIDENCE``: the SDK skips the point head, which the official forward computes);
2. measures the best bf16 rate of ``F.linear`` on this CPU over the step's own linear shapes
   (T tokens x dim -> 3·dim, dim, mlp·dim; and back), on 1 thread and on every usable core; the
   attention products are bounded at that same rate (their kernels run below it on CPUs without
   AMX, so the bound is generous);
3. times the official cached step as the official forward runs it (``auto_choice.
   _official_step``: fp32 weights under bf16 autocast, every head), median of ``--repeats``;
4. reports bound = official time / (step FLOPs / best rate): no exact implementation of this
   step on this machine can be faster than that, whatever its kernels; and, timed in the same
   interleaved rounds, the SDK's torch bf16 step: its speed-up and the share of that floor it
   reaches.

Run from the repository root (Pi3 ``large`` at 224, N = 8: about three minutes, 4 GB)::

    OMP_WAIT_POLICY=PASSIVE python -m benchmarks.step_bound --model pi3-large --size 224 --keyframes 8

Writes ``benchmarks/results/<--name>.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F

from benchmarks.auto_choice import _cpu, _official_step
from benchmarks.flops import tracking_step_flops
from benchmarks.model_families import build_model
from kvtracker_sdk.backends.autotune import synthetic_frames
from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.models.pi3 import Pi3
from kvtracker_sdk.threads import usable_cores
from kvtracker_sdk.types import HeadSet

RESULTS = Path(__file__).parent / "results"


def linear_shapes(model: Pi3, tokens: int) -> list[tuple[int, int, int]]:
    """(rows, in, out) of the step's transformer linears: qkv, proj, MLP up and down."""
    shapes = set()
    for dim, ratio in ((model.config.encoder.embed_dim, model.config.encoder.mlp_ratio),
                       (model.config.decoder.embed_dim, model.config.decoder.mlp_ratio)):  # fmt: skip
        hidden = int(dim * ratio)
        shapes |= {(tokens, dim, 3 * dim), (tokens, dim, dim), (tokens, dim, hidden),
                   (tokens, hidden, dim)}  # fmt: skip
    return sorted(shapes)


def best_linear_rate(shapes: list[tuple[int, int, int]], threads: int, repeats: int) -> dict[str, Any]:
    """The highest bf16 ``F.linear`` FLOP/s over ``shapes`` on ``threads`` threads (best of
    ``repeats`` timed calls per shape, after two warm-ups)."""
    torch.set_num_threads(threads)
    generator = torch.Generator().manual_seed(0)
    rates = {}
    for rows, fan_in, fan_out in shapes:
        x = torch.randn(rows, fan_in, generator=generator).bfloat16()
        w = torch.randn(fan_out, fan_in, generator=generator).bfloat16()
        for _ in range(2):
            F.linear(x, w)
        best = float("inf")
        for _ in range(repeats):
            start = time.perf_counter()
            F.linear(x, w)
            best = min(best, time.perf_counter() - start)
        rates[f"{rows}x{fan_in}x{fan_out}"] = 2.0 * rows * fan_in * fan_out / best
    return {"best_flops_per_s": max(rates.values()), "per_shape": rates}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="pi3-large")
    parser.add_argument("--size", type=int, default=224)
    parser.add_argument("--keyframes", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--name", default="step_bound")
    args = parser.parse_args(argv)
    model = build_model(args.model, torch.float32)
    if not isinstance(model, Pi3):
        parser.error("the FLOP model (benchmarks/flops.py) counts Pi3 only")
    flops = tracking_step_flops(model.config, args.size, args.size, args.keyframes,
                                HeadSet.CONFIDENCE)  # fmt: skip
    step, total = flops.to_dict(), flops.total
    patches = (args.size // model.config.patch_size) ** 2
    tokens = model.config.decoder.num_register_tokens + patches
    images = synthetic_frames(args.keyframes + 1, args.size, args.size)
    cache = TorchBackend(model, threads=usable_cores()).map(images[: args.keyframes]).cache
    cache16 = cache.to(dtype=torch.bfloat16)
    sdk_backend = TorchBackend(build_model(args.model, torch.float32), dtype="bfloat16")
    frame = images[args.keyframes]
    rows = []
    for threads in sorted({1, usable_cores()}):
        rate = best_linear_rate(linear_shapes(model, tokens), threads, args.repeats)
        official = _official_step(model, cache16, frame, torch.bfloat16, threads)

        def sdk(threads: int = threads) -> object:
            torch.set_num_threads(threads)
            return sdk_backend.track(frame, cache16, heads=HeadSet.CONFIDENCE)

        times: dict[str, list[float]] = {"official": [], "sdk": []}
        official(), sdk()  # untimed first calls
        for _ in range(args.repeats):  # interleaved: a load change hits both
            for name, timed_step in (("official", official), ("sdk", sdk)):
                start = time.perf_counter()
                timed_step()
                times[name].append(time.perf_counter() - start)
        floor = total / rate["best_flops_per_s"]
        official_s, sdk_s = statistics.median(times["official"]), statistics.median(times["sdk"])
        rows.append({"threads": threads, "official_s": official_s, "sdk_s": sdk_s,
                     "samples_s": times, "linear_rate": rate, "floor_s": floor,
                     "bound": official_s / floor, "sdk_speedup": official_s / sdk_s,
                     "sdk_of_roofline": floor / sdk_s, "load": os.getloadavg()})  # fmt: skip
        print(f"t{threads}: official {official_s:.3f} s, SDK bf16 {sdk_s:.3f} s, floor {floor:.3f}"
              f" s at {rate['best_flops_per_s'] / 1e9:.0f} GFLOP/s -> bound {rows[-1]['bound']:.2f}x"
              f", SDK {rows[-1]['sdk_speedup']:.2f}x", flush=True)  # fmt: skip
    result = {
        "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": "OMP_WAIT_POLICY=PASSIVE python -m benchmarks.step_bound "
                   + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": {"cpu": _cpu(), "usable_cores": usable_cores(), "torch": torch.__version__,
                    "cpu_capability": torch.backends.cpu.get_cpu_capability(),
                    "platform": platform.platform()},
        "model": args.model, "size": args.size, "keyframes": args.keyframes,
        "step_flops": step, "step_flops_total": total, "rows": rows,
    }  # fmt: skip
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{args.name}.json").write_text(json.dumps(result, indent=1) + "\n")
    (RESULTS / f"{args.name}.md").write_text(_table(result))
    return result


def _table(result: dict[str, Any]) -> str:
    machine = result["machine"]
    lines = [
        f"# Roofline bound of a tracking step — {machine['cpu']}, {machine['usable_cores']} cores "
        f"({machine['cpu_capability']}), {result['date_utc']}", "",
        f"`{result['command']}`", "",
        f"{result['model']} {result['size']}x{result['size']}, N = {result['keyframes']}: the step "
        f"the SDK computes (camera + confidence heads) is "
        f"{result['step_flops_total'] / 1e9:.0f} GFLOP.", "",
        "| threads | official step (s) | SDK torch bf16 step (s) | SDK speed-up "
        "| best bf16 linear rate (GFLOP/s) | floor: FLOPs / rate (s) | bound on speed-up "
        "| SDK at % of floor | load avg |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]  # fmt: skip
    for row in result["rows"]:
        lines.append(
            f"| {row['threads']} | {row['official_s']:.3f} | {row['sdk_s']:.3f} | "
            f"{row['sdk_speedup']:.2f}× | {row['linear_rate']['best_flops_per_s'] / 1e9:.0f} | "
            f"{row['floor_s']:.3f} | {row['bound']:.2f}× | {100 * row['sdk_of_roofline']:.0f} % | "
            f"{row['load'][0]:.2f} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()

"""Where the cached global attention's time goes: attention kernels against the matrix-product rate.

One tracking step's global layer attends from one frame's T queries over (N+1)·T keys (the cache
plus the frame's own tokens; ``Attention.forward_track``). For the head shapes of DA3-Small (6
heads) and Pi3 ``large`` (16 heads), head_dim 64, at N = ``--keyframes``, this times in
interleaved rounds (process CPU time, ``--threads``):

- ``sdpa-bf16``: what the SDK runs in bf16, ``F.scaled_dot_product_attention`` (CPU flash kernel);
- ``sdpa-fp32in``: the same kernel on operands cast to fp32 (fp32 probabilities);
- ``products-fp32``: two batched products with the scores in fp32 (q, k cast to fp32), the
  softmax in fp32, P in bf16 for P·V, one head at a time (the scores of all heads at N = 32 would
  be tens of MB);
- ``products-bf16``: both products in bf16 (scores rounded to bf16 before an fp32 softmax), 64
  queries at a time;
- GEMM probes ``[1024 x 1024] x [1024 x 4096]`` in bf16 and fp32: the rates the kernels could reach.

Each kernel's output is compared with a float64 reference (max abs error, same inputs). The random
queries are scaled so that scores spread over a few units, as in trained attention.

    python -m benchmarks.attention_kernels --keyframes 8 32 64

Writes ``benchmarks/results/<--name>.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F

RESULTS = Path(__file__).parent / "results"
SHAPES = {"da3-small": (6, 257), "pi3-large": (16, 261)}  # heads, tokens per frame at 224²
HEAD_DIM = 64
Kernel = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


def sdpa(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return F.scaled_dot_product_attention(q, k, v)


def sdpa_fp32_inputs(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return F.scaled_dot_product_attention(q.float(), k.float(), v.float()).to(v.dtype)


def products_fp32_scores(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    out = torch.empty_like(q)
    for head in range(q.shape[1]):
        scores = torch.matmul(q[:, head].float() * HEAD_DIM**-0.5, k[:, head].float().mT)
        weights = scores.sub_(scores.amax(-1, keepdim=True)).exp_()
        total = weights.sum(-1, keepdim=True)
        out[:, head] = torch.matmul(weights.to(v.dtype), v[:, head]) / total
    return out


def products_bf16_scores(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    out, keys = torch.empty_like(q), k.mT
    for start in range(0, q.shape[2], 64):
        scores = torch.matmul(q[:, :, start : start + 64] * HEAD_DIM**-0.5, keys)
        weights = torch.softmax(scores, -1, dtype=torch.float32).to(v.dtype)
        out[:, :, start : start + 64] = torch.matmul(weights, v)
    return out


KERNELS: dict[str, Kernel] = {
    "sdpa-bf16": sdpa,
    "sdpa-fp32in": sdpa_fp32_inputs,
    "products-fp32": products_fp32_scores,
    "products-bf16": products_bf16_scores,
}


def measure(model: str, keyframes: int, args: argparse.Namespace) -> dict[str, Any]:
    heads, tokens = SHAPES[model]
    keys_count = (keyframes + 1) * tokens
    gen = torch.Generator().manual_seed(keyframes)
    q = (torch.randn(1, heads, tokens, HEAD_DIM, generator=gen) * 2).to(torch.bfloat16)
    k = torch.randn(1, heads, keys_count, HEAD_DIM, generator=gen).to(torch.bfloat16)
    v = torch.randn(1, heads, keys_count, HEAD_DIM, generator=gen).to(torch.bfloat16)
    reference = F.scaled_dot_product_attention(q.double(), k.double(), v.double())
    a16, b16 = torch.randn(1024, 1024).bfloat16(), torch.randn(1024, 4096).bfloat16()
    a32, b32 = a16.float(), b16.float()
    calls: dict[str, Callable[[], Any]] = {
        name: (lambda kernel=kernel: kernel(q, k, v)) for name, kernel in KERNELS.items()
    }
    calls["gemm-bf16"] = lambda: torch.mm(a16, b16)
    calls["gemm-fp32"] = lambda: torch.mm(a32, b32)
    best = dict.fromkeys(calls, float("inf"))
    names = list(calls)
    for name in names:  # warm-up
        calls[name]()
    for round_index in range(args.rounds):
        shift = round_index % len(names)
        for name in names[shift:] + names[:shift]:
            start = time.process_time()
            calls[name]()
            best[name] = min(best[name], time.process_time() - start)
    flops = 4.0 * heads * tokens * keys_count * HEAD_DIM
    gemm = 2.0 * 1024 * 1024 * 4096
    return {
        "model": model, "keyframes": keyframes, "heads": heads, "queries": tokens,
        "keys": keys_count, "flops": flops,
        "seconds": {name: best[name] for name in KERNELS},
        "gflops": {name: flops / best[name] / 1e9 for name in KERNELS},
        "gemm_gflops": {"bf16": gemm / best["gemm-bf16"] / 1e9,
                        "fp32": gemm / best["gemm-fp32"] / 1e9},
        "max_error": {name: float((kernel(q, k, v).double() - reference).abs().max())
                      for name, kernel in KERNELS.items()},
    }  # fmt: skip


def markdown_table(rows: list[dict[str, Any]]) -> str:
    names = list(KERNELS)
    lines = [
        "| shape | N | keys | " + " | ".join(f"{n} ms (GFLOP/s, max err)" for n in names)
        + " | GEMM bf16 / fp32 GFLOP/s |",
        "|---|---:|---:|" + "---:|" * len(names) + "---:|",
    ]
    for row in rows:
        cells = [f"{row['seconds'][n] * 1e3:.1f} ({row['gflops'][n]:.0f}, "
                 f"{row['max_error'][n]:.0e})" for n in names]  # fmt: skip
        lines.append(
            f"| {row['model']} ({row['heads']} heads) | {row['keyframes']} | {row['keys']} | "
            + " | ".join(cells)
            + f" | {row['gemm_gflops']['bf16']:.0f} / {row['gemm_gflops']['fp32']:.0f} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", choices=list(SHAPES), default=list(SHAPES))
    parser.add_argument("--keyframes", nargs="+", type=int, default=[8, 32, 64])
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--name", default="attention_kernels")
    parser.add_argument("--out-dir", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    load_start = os.getloadavg()
    rows = [measure(model, n, args) for model in args.models for n in args.keyframes]
    result = {
        "threads": args.threads, "rounds": args.rounds, "clock": "cpu",
        "cpu_capability": torch.backends.cpu.get_cpu_capability(), "torch": torch.__version__,
        "load_average_start": load_start, "load_average_end": os.getloadavg(), "rows": rows,
    }  # fmt: skip
    args.out_dir.mkdir(parents=True, exist_ok=True)
    (args.out_dir / f"{args.name}.json").write_text(json.dumps(result, indent=1) + "\n")
    print(markdown_table(rows))
    print(f"load average {load_start[0]:.1f} -> {result['load_average_end'][0]:.1f}")
    return result


if __name__ == "__main__":
    main()

"""Cached tracking step vs full recompute: time and FLOPs against the number of keyframes N.

For each N, one query frame is tracked against a cache of N keyframes (``Pi3.forward_track``)
and, for comparison, the full model runs on the N + 1 frames (``Pi3.forward``) — the cost of
tracking without a cache. Both sides compute the same heads. The cache is filled with random K/V
(content does not change the work); a check at start-up builds a real cache with
``forward_map`` and verifies that it has the same buffers and that tracking through it matches
the masked full forward, so the timed path is the real one.

Timing: tracking steps run in ``--warmup`` + ``--repeats`` round-robin rounds over all N and head
sets (all caches held at once); each recompute gets ``--warmup`` untimed calls (N <= 8 only), then
up to ``--repeats`` timed calls, fewer once it has taken ``--budget`` seconds. Wall and process CPU
time are both recorded; the table uses the best (minimum) on ``--clock``, the least disturbed
sample on a shared machine. Load averages are recorded at start, per N and at the end.

Run from the repository root::

    python -m benchmarks.tracking_vs_recompute --config mid --size 308 --dtype bf16
    python -m benchmarks.tracking_vs_recompute --config large --size 224 --max-recompute 16
    python -m benchmarks.tracking_vs_recompute --config large --size 196 252  # H W: d=224, 4:3

Writes ``benchmarks/results/<name>.json`` and ``<name>.png`` (``--name``, default
``<config>_<size>_<dtype>``, size ``S`` or ``HxW``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import torch

from benchmarks.flops import recompute_flops, tracking_step_flops
from benchmarks.tracking_report import plot_fps, print_tables
from kvtracker_sdk.cache import CacheLayout, KVCache
from kvtracker_sdk.models.layers.attention import keyframe_query_mask
from kvtracker_sdk.models.pi3 import (
    Pi3,
    Pi3Config,
    Pi3DecoderConfig,
    Pi3EncoderConfig,
    Pi3HeadsConfig,
)
from kvtracker_sdk.types import HeadSet

RESULTS = Path(__file__).parent / "results"
DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16}
HEADS = {"camera": HeadSet.CAMERA, "conf": HeadSet.CONFIDENCE, "all": HeadSet.ALL}
# max |pose difference| between tracking through a forward_map cache and the masked forward
CHECK_TOLERANCE = {"fp32": 1e-3, "bf16": 5e-2}

PRESETS: dict[str, Callable[[], Pi3Config]] = {
    "large": Pi3Config.large,
    # ViT-S-like depth (12 blocks) at the decoder's width (Pi3 feeds the encoder tokens to the
    # decoder unprojected, so both are 512 wide); a 12-block decoder: 6 cached global layers.
    "mid": lambda: Pi3Config(
        encoder=Pi3EncoderConfig(embed_dim=512, depth=12, num_heads=8),
        decoder=Pi3DecoderConfig(embed_dim=512, depth=12, num_heads=8),
        heads=Pi3HeadsConfig(
            embed_dim=512, depth=2, num_heads=8, point_out_dim=512, camera_out_dim=256
        ),
    ),
    # a few seconds end to end: the smoke test's config
    "tiny": lambda: Pi3Config(
        encoder=Pi3EncoderConfig(embed_dim=32, depth=1, num_heads=2, pos_embed_grid=6),
        decoder=Pi3DecoderConfig(embed_dim=32, depth=4, num_heads=2),
        heads=Pi3HeadsConfig(
            embed_dim=16, depth=1, num_heads=2, point_out_dim=16, camera_out_dim=16
        ),
    ),
}


def build_model(config: Pi3Config, dtype: torch.dtype, seed: int = 0) -> Pi3:
    """A Pi3 with PyTorch's default random init in ``dtype`` (final heads fp32), eval mode."""
    torch.manual_seed(seed)
    model = Pi3(config).eval().set_precision(dtype)
    return model.requires_grad_(False)


def cache_layout(model: Pi3) -> CacheLayout:
    dec = model.config.decoder
    return CacheLayout(dec.global_block_indices, dec.num_heads, dec.head_dim)


def random_cache(model: Pi3, keyframes: int, tokens_per_frame: int) -> KVCache:
    """A cache of ``keyframes`` frames built like a mapping pass's (``KVCache.from_layers``).

    Every layer gets the same random block: the values do not change the work, and one block
    instead of 2 x layers keeps the peak memory at the cache's own size.
    """
    layout = cache_layout(model)
    shape = (1, layout.num_heads, keyframes * tokens_per_frame, layout.head_dim)
    block = torch.randn(shape, generator=torch.Generator().manual_seed(keyframes))
    block = block.to(model.compute_dtype)
    layers = [block] * layout.num_layers
    return KVCache.from_layers(
        layers, layers, layout=layout, tokens_per_frame=tokens_per_frame,
        keyframe_ids=list(range(keyframes)),
    )  # fmt: skip


@torch.no_grad()
def check_real_path(
    model: Pi3, size: tuple[int, int], dtype_name: str, keyframes: int = 2
) -> float:
    """Build a cache by ``forward_map``; check it matches ``random_cache`` and tracks correctly.

    Returns max |pose difference| between tracking the query through the real cache and the
    full forward on [keyframes, query] under the keyframe/query mask. Raises RuntimeError
    when the buffers differ or the difference exceeds ``CHECK_TOLERANCE``.
    """
    imgs = torch.rand(1, keyframes + 1, 3, *size, generator=torch.Generator().manual_seed(7))
    mapped = model.forward_map(imgs[:, :keyframes], heads=HeadSet.CAMERA)
    tokens = mapped.tokens_per_frame
    real = KVCache.from_layers(
        mapped.keys, mapped.values, layout=cache_layout(model), tokens_per_frame=tokens,
        keyframe_ids=list(range(keyframes)),
    )  # fmt: skip
    fake = random_cache(model, keyframes, tokens)
    for layer in range(real.layout.num_layers):
        for a, b in zip(real.buffers(layer), fake.buffers(layer), strict=True):
            if (a.shape, a.dtype, a.stride()) != (b.shape, b.dtype, b.stride()):
                raise RuntimeError(f"cache buffers differ: {tuple(a.shape)} vs {tuple(b.shape)}")
    tracked = model.forward_track(imgs[0, keyframes:], real, heads=HeadSet.CAMERA).camera_poses
    mask = keyframe_query_mask(keyframes * tokens, 1, tokens)
    full = model(imgs, heads=HeadSet.CAMERA, global_attn_mask=mask).camera_poses[:, keyframes:]
    error = float((tracked - full).abs().max())
    if error > CHECK_TOLERANCE[dtype_name]:
        raise RuntimeError(f"tracking != masked forward: max |pose diff| {error:.2e}")
    return error


def time_once(fn: Callable[[], object]) -> tuple[float, float]:
    """(wall, process CPU) seconds of one call."""
    start_wall, start_cpu = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - start_wall, time.process_time() - start_cpu


def time_call(fn: Callable[[], object], warmup: int, repeats: int, budget: float) -> dict[str, Any]:
    """Wall and CPU seconds of ``repeats`` calls after ``warmup``; stops early past ``budget`` s."""
    for _ in range(warmup):
        fn()
    samples: dict[str, list[float]] = {"wall": [], "cpu": []}
    while len(samples["wall"]) < max(1, repeats) and sum(samples["wall"]) < budget:
        wall, cpu = time_once(fn)
        samples["wall"].append(wall)
        samples["cpu"].append(cpu)
    return samples


@torch.no_grad()
def time_tracking(
    model: Pi3, query: torch.Tensor, args: argparse.Namespace
) -> list[dict[str, Any]]:
    """One row per N: tracking ``query`` [1, 3, H, W] against N random keyframes, per head set.

    The calls go round-robin (every N and head set once per round, ``--warmup`` + ``--repeats``
    rounds) so that a busy spell on a shared machine hits all N alike instead of one N's points.
    """
    height, width = query.shape[-2:]
    tokens = model.tokens_per_frame(height, width)
    caches = {n: random_cache(model, n, tokens) for n in args.keyframes}
    rows: dict[int, dict[str, Any]] = {
        n: {"keyframes": n, "cache_bytes": cache.nbytes} for n, cache in caches.items()
    }
    for round_index in range(args.warmup + args.repeats):
        for n, cache in caches.items():
            for name in args.heads:
                step = partial(model.forward_track, query, cache, heads=HEADS[name])
                wall, cpu = time_once(step)
                if round_index >= args.warmup:
                    samples = rows[n].setdefault(f"track_{name}", {"wall": [], "cpu": []})
                    samples["wall"].append(wall)
                    samples["cpu"].append(cpu)
    for n, row in rows.items():
        for name in args.heads:
            row[f"track_{name}_flops"] = tracking_step_flops(
                model.config, height, width, n, HEADS[name]
            ).to_dict()
            row[f"recompute_{name}_flops"] = recompute_flops(
                model.config, height, width, n + 1, HEADS[name]
            ).to_dict()
    return list(rows.values())


@torch.no_grad()
def time_recompute(frames: torch.Tensor, model: Pi3, args: argparse.Namespace) -> dict[str, Any]:
    """The full forward on ``frames`` [1, N+1, 3, H, W], per head set."""
    # a recompute costs ~N+1 tracking steps: a warmup call only for short ones
    warmup = args.warmup if frames.shape[1] <= 9 else 0
    return {
        f"recompute_{name}": time_call(
            partial(model, frames, heads=HEADS[name]), warmup, args.repeats, args.budget
        )
        for name in args.heads
    }


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", choices=sorted(PRESETS), default="mid")
    parser.add_argument("--dtype", choices=sorted(DTYPES), default="bf16")
    parser.add_argument("--size", type=int, nargs="+", default=[308], metavar="PX",
                        help="S (a square) or H W in px, multiples of 14")  # fmt: skip
    parser.add_argument("--keyframes", type=int, nargs="+", default=[1, 2, 4, 8, 16, 32, 64])
    parser.add_argument("--max-recompute", type=int, default=32, help="largest N to recompute")
    parser.add_argument("--heads", choices=sorted(HEADS), nargs="+", default=["camera", "all"])
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--budget", type=float, default=30.0, help="seconds per point")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--clock", choices=["wall", "cpu"], default="wall")
    parser.add_argument("--name", help="output file stem (default <config>_<size>_<dtype>)")
    parser.add_argument("--out-dir", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if len(args.size) > 2:
        parser.error("--size takes S or H W")
    return args


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the benchmark; print the tables, write JSON and PNG; return the JSON content."""
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    load_start = os.getloadavg()
    config = PRESETS[args.config]()
    dtype = DTYPES[args.dtype]
    model = build_model(config, dtype)
    size = (args.size[0], args.size[-1])  # (H, W)
    tokens = model.tokens_per_frame(*size)
    print(f"config {args.config}: {config.model_dump_json()}")
    print(f"{args.dtype}, {size[0]}x{size[1]} px, T={tokens} tokens/frame, {args.threads} threads, "
          f"torch {torch.__version__}, load average {load_start}")  # fmt: skip
    check_error = check_real_path(model, size, args.dtype)
    print(f"real-path check: forward_track(forward_map cache) vs masked forward, "
          f"max |pose diff| {check_error:.2e}")  # fmt: skip

    size_name = str(size[0]) if size[0] == size[1] else f"{size[0]}x{size[1]}"
    name = args.name or f"{args.config}_{size_name}_{args.dtype}"
    args.out_dir.mkdir(parents=True, exist_ok=True)
    json_path = args.out_dir / f"{name}.json"
    result: dict[str, Any] = {
        "config_name": args.config,
        "config": config.model_dump(),
        "dtype": args.dtype,
        "resolution": list(size),
        "tokens_per_frame": tokens,
        "heads": args.heads,
        "clock": args.clock,
        "warmup": args.warmup,
        "repeats": args.repeats,
        "budget_seconds": args.budget,
        "threads": args.threads,
        "real_path_check_max_pose_diff": check_error,
        "load_average_start": load_start,
        "machine": {"cpus": os.cpu_count(), "processor": platform.processor(),
                    "platform": platform.platform(), "torch": torch.__version__,
                    "cpu_capability": torch.backends.cpu.get_cpu_capability(),
                    "python": platform.python_version()},
        "rows": [],
    }  # fmt: skip
    generator = torch.Generator().manual_seed(0)
    query = torch.rand(1, 3, *size, generator=generator)
    result["rows"] = time_tracking(model, query, args)
    print(f"tracking timed, load average {os.getloadavg()}", flush=True)
    for row in result["rows"]:
        n = row["keyframes"]
        if n <= args.max_recompute:
            frames = torch.rand(1, n + 1, 3, *size, generator=generator)
            row |= time_recompute(frames, model, args)
        row["load_average"] = os.getloadavg()
        print(f"N={n} done, load average {row['load_average']}", flush=True)
        # rewritten after every N: a long run that is stopped keeps what it measured
        result["load_average_end"] = os.getloadavg()
        json_path.write_text(json.dumps(result, indent=2) + "\n")

    print_tables(result)
    plot_fps(result, json_path.with_suffix(".png"))
    print(f"wrote {json_path} and {json_path.with_suffix('.png').name}")
    return result


if __name__ == "__main__":
    main()

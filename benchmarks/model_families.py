"""Tracking speed of the model families: a cached step against N keyframes, DA3 vs Pi3.

For each model (``--models``: ``da3-small``, ``da3-base``, ``pi3-large``, random weights: the
work does not depend on them), dtype (``--dtypes``) and thread count (``--threads``; default
torch's default, then 1) this measures the tracking step ``forward_track`` of one query frame
against N random keyframes (``--keyframes``; Pi3: ``--pi3-keyframes``, a step takes seconds),
camera head only, and with the tracker's default heads (``HeadSet.CONFIDENCE``) at
``--headline-keyframes``; the mapping pass ``forward_map`` on ``--map-keyframes`` frames with
the heads ``TorchBackend`` maps with (its K/V also check the random caches' layout); and the
cache bytes per keyframe.

Timing (``shared_cpu_timing``): round-robin rounds over a group's points, wall and process CPU
time per call, the minimum reported. Each round also records the cores other processes used
meanwhile; a round is contended when they used more than the cores the run leaves free plus
``--max-others``. Rounds repeat (waiting for quiet, ``--max-wait`` s per group stage) until every
point has ``--repeats`` clean samples, ``3 * --repeats`` rounds ran or ``--budget`` s passed;
the tables use clean samples only (``*``: none was clean). ``--update`` re-measures some groups
into an existing JSON, e.g. when a quieter spell comes.

Frames are ``--size`` squares unless ``--pi3-size`` / ``--da3-size`` give a family its own H x W
(the sizes the preprocessing gives a 640x480 frame: Pi3 at d=224 196x252, DA3 by default 378x504).

Run from the repository root (about half an hour on a quiet 2-core CPU, most of it Pi3)::

    python -m benchmarks.model_families
    python -m benchmarks.model_families --models da3-small --threads 2

Writes ``benchmarks/results/<--name>.json`` (default ``model_families``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import torch
from torch import nn

from benchmarks.shared_cpu_timing import best, measure_rounds, new_samples, wait_for_quiet
from benchmarks.tracking_vs_recompute import DTYPES, PRESETS
from kvtracker_sdk.cache import CacheLayout, KVCache
from kvtracker_sdk.models.da3 import (
    DA3BackboneConfig,
    DA3CameraEncoderConfig,
    DA3Config,
    DA3HeadConfig,
    DepthAnything3,
)
from kvtracker_sdk.models.pi3 import Pi3, Pi3Config
from kvtracker_sdk.models.registry import family_of
from kvtracker_sdk.types import HeadSet

RESULTS = Path(__file__).parent / "results"
TRACK_HEADS = {"camera": HeadSet.CAMERA, "conf": HeadSet.CONFIDENCE}
MAP_HEADS = {"da3": HeadSet.CONFIDENCE, "pi3": HeadSet.ALL}  # as ``TorchBackend`` maps
TARGET = {"model": "da3-small", "dtype": "bf16", "keyframes": 8, "seconds": 0.12}

_TINY_DA3 = DA3Config(
    backbone=DA3BackboneConfig(
        embed_dim=32, depth=6, num_heads=2, alt_start=2, out_layers=(2, 3, 4, 5), pos_embed_grid=4
    ),
    head=DA3HeadConfig(features=8, out_channels=(4, 4, 8, 8)),
    cam_enc=DA3CameraEncoderConfig(depth=1, num_heads=2),
)
# name -> (network factory, weights licence); the tiny ones are the smoke test's
MODELS: dict[str, tuple[Callable[[], nn.Module], str]] = {
    "da3-small": (lambda: DepthAnything3(DA3Config.small()), "Apache-2.0"),
    "da3-base": (lambda: DepthAnything3(DA3Config.base()), "Apache-2.0"),
    "pi3-large": (lambda: Pi3(Pi3Config.large()), "CC BY-NC 4.0"),
    "da3-tiny": (lambda: DepthAnything3(_TINY_DA3), "test"),
    "pi3-tiny": (lambda: Pi3(PRESETS["tiny"]()), "test"),
}


def build_model(name: str, dtype: torch.dtype, seed: int = 0) -> nn.Module:
    """``name``'s network with PyTorch's random init, trunk in ``dtype`` (heads fp32), eval."""
    torch.manual_seed(seed)
    model = MODELS[name][0]().eval()
    return model.set_precision(dtype).requires_grad_(False)  # type: ignore[operator]


def random_cache(layout: CacheLayout, dtype: torch.dtype, keyframes: int, tokens: int) -> KVCache:
    """A ``from_layers`` cache of random K/V (one block shared by the layers: values do not
    change the work, and the peak memory stays the cache's own size)."""
    shape = (1, layout.num_heads, keyframes * tokens, layout.head_dim)
    block = torch.randn(shape, generator=torch.Generator().manual_seed(keyframes)).to(dtype)
    layers = [block] * layout.num_layers
    return KVCache.from_layers(
        layers, layers, layout=layout, tokens_per_frame=tokens, keyframe_ids=range(keyframes)
    )


def _limits(args: argparse.Namespace) -> dict[str, float]:
    return {"budget": args.budget, "max_wait": args.max_wait}


@torch.no_grad()
def time_group(
    model: Any, keyframes: Sequence[int], args: argparse.Namespace, allowed: float
) -> list[dict[str, Any]]:
    """One row per N: the tracking step against N random keyframes, camera head only, plus the
    tracker's default heads at ``--headline-keyframes``."""
    layout, (height, width) = family_of(model).cache_layout(model), frame_size(args, model)
    tokens = model.tokens_per_frame(height, width)
    caches = {n: random_cache(layout, model.compute_dtype, n, tokens) for n in keyframes}
    query = torch.rand(1, 3, height, width, generator=torch.Generator().manual_seed(0))
    rows = {n: {"keyframes": n, "cache_bytes": cache.nbytes} for n, cache in caches.items()}
    calls = []
    for n in keyframes:
        for heads in ("camera", "conf") if n == args.headline_keyframes else ("camera",):
            samples = rows[n][f"track_{heads}"] = new_samples()
            step = partial(model.forward_track, query, caches[n], heads=TRACK_HEADS[heads])
            calls.append((samples, step))
    measure_rounds(calls, allowed, repeats=args.repeats, warmup=args.warmup, **_limits(args))
    return list(rows.values())


@torch.no_grad()
def time_mapping(
    model: Any, family: str, args: argparse.Namespace, allowed: float
) -> dict[str, Any]:
    """``--map-repeats`` clean mapping passes on ``--map-keyframes`` frames (the minimum absorbs
    the first call's warm-up), then a check that their K/V make a cache laid out like
    ``random_cache``'s — so the timed tracking path reads the real layout."""
    n, (height, width), heads = args.map_keyframes, frame_size(args, model), MAP_HEADS[family]
    frames = torch.rand(1, n, 3, height, width, generator=torch.Generator().manual_seed(1))
    samples, last = new_samples(), []

    def mapping() -> None:
        last.clear()  # keep one pass's K/V at a time
        last.append(model.forward_map(frames, heads=heads))

    measure_rounds(
        [(samples, mapping)], allowed, repeats=args.map_repeats, warmup=0, **_limits(args)
    )
    layout, tokens = family_of(model).cache_layout(model), last[0].tokens_per_frame
    real = KVCache.from_layers(last[0].keys, last[0].values, layout=layout,
                               tokens_per_frame=tokens, keyframe_ids=range(n))  # fmt: skip
    fake = random_cache(layout, model.compute_dtype, n, tokens)
    for a, b in zip(real.buffers(0), fake.buffers(0), strict=True):
        layouts = [(t.shape, t.dtype, t.stride()) for t in (a, b)]
        assert layouts[0] == layouts[1], f"mapped vs random cache: {layouts}"
    return {"keyframes": n, "heads": heads.value, **samples}


def markdown_table(result: dict[str, Any], threads: int, clock: str) -> str:
    """One line per model and dtype at ``threads``: seconds per tracking step (camera head) by
    N; FPS and the step with the tracker's default heads at the headline N; the mapping pass;
    the cache per keyframe. ``*``: every sample of that point was contended."""
    ns, headline = result["keyframes"], result["headline_keyframes"]
    names = [*(f"N={n}" for n in ns), f"FPS N={headline}", f"+conf N={headline}",
             f"map {result['map_keyframes']} KF", "cache/KF"]  # fmt: skip
    lines = ["| model (weights) | dtype | " + " | ".join(names) + " |"]
    lines.append("|---|---|" + "---:|" * len(names))
    for group in (g for g in result["groups"] if g["threads"] == threads):
        rows = {row["keyframes"]: row for row in group["rows"]}

        def seconds(samples: dict[str, list[float]] | None, group: dict[str, Any] = group) -> str:
            found = best(samples, clock, group["allowed_others"])
            return "—" if found is None else f"{found[0]:.3f}" + ("" if found[1] else "*")

        step = best(rows.get(headline, {}).get("track_camera"), clock, group["allowed_others"])
        cells = [
            f"{group['model']} ({group['licence']}), {group['size'][0]}×{group['size'][1]}",
            group["dtype"],
            *(seconds(rows.get(n, {}).get("track_camera")) for n in ns),
            "—" if step is None else f"{1 / step[0]:.1f}",
            seconds(rows.get(headline, {}).get("track_conf")),
            seconds(group["map"]),
            f"{group['cache_bytes_per_keyframe'] / 1e6:.3g} MB",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add = parser.add_argument
    add("--models", choices=list(MODELS), nargs="+", default=["da3-small", "da3-base", "pi3-large"])
    add("--dtypes", choices=sorted(DTYPES), nargs="+", default=["bf16", "fp32"])
    add("--size", type=int, default=224, help="square side in px, multiple of 14")
    add("--pi3-size", type=int, nargs=2, metavar=("H", "W"),
        help="Pi3 frames H x W (default --size square), e.g. 196 252: Pi3 at d=224 for 640x480")  # fmt: skip
    add("--da3-size", type=int, nargs=2, metavar=("H", "W"),
        help="DA3 frames H x W (default --size square), e.g. 378 504: DA3's default for 640x480")  # fmt: skip
    add("--keyframes", type=int, nargs="+", default=[1, 2, 4, 8, 16, 32])
    add("--pi3-keyframes", type=int, nargs="+", default=[1, 8, 32], help="N for Pi3 models")
    add("--headline-keyframes", type=int, default=8, help="N of the FPS and +conf columns")
    add("--map-keyframes", type=int, default=8)
    add("--map-repeats", type=int, default=3)
    add("--warmup", type=int, default=1, help="untimed rounds per group")
    add("--repeats", type=int, default=5, help="clean samples wanted per point")
    add("--budget", type=float, default=120.0, help="seconds of timed rounds per group")
    add("--threads", type=int, nargs="+", default=[torch.get_num_threads(), 1])
    add("--clock", choices=["wall", "cpu"], default="wall")
    add("--max-others", type=float, default=0.25,
        help="cores other processes may use beyond those the run leaves free")  # fmt: skip
    add("--max-wait", type=float, default=300.0,
        help="seconds to wait for quiet, per stage of a group (start, tracking, mapping)")  # fmt: skip
    add("--name", default="model_families", help="output file stem")
    add("--out-dir", type=Path, default=RESULTS)
    add("--update", action="store_true",
        help="keep the other groups of an existing JSON (re-measure some on a quieter machine)")  # fmt: skip
    args = parser.parse_args(argv)
    args.threads = list(dict.fromkeys(args.threads))
    return args


def frame_size(args: argparse.Namespace, model: Any) -> tuple[int, int]:
    """(H, W) of the frames for ``model``'s family: ``--pi3-size`` / ``--da3-size``, else square."""
    chosen = args.pi3_size if isinstance(model, Pi3) else args.da3_size
    return (chosen[0], chosen[1]) if chosen else (args.size, args.size)


def run_group(
    model: Any, name: str, dtype: str, threads: int, args: argparse.Namespace
) -> dict[str, Any]:
    """Everything measured for one model, dtype and thread count (after waiting for quiet)."""
    family = "pi3" if isinstance(model, Pi3) else "da3"
    torch.set_num_threads(threads)
    cpus = os.cpu_count() or 1
    allowed = max(0, cpus - threads) + args.max_others
    size = frame_size(args, model)
    tokens = model.tokens_per_frame(*size)
    layout = family_of(model).cache_layout(model)
    group: dict[str, Any] = {
        "model": name, "family": family, "licence": MODELS[name][1], "dtype": dtype,
        "threads": threads, "params": sum(p.numel() for p in model.parameters()),
        "size": list(size),
        "tokens_per_frame": tokens,
        "cache_bytes_per_keyframe": tokens * layout.bytes_per_token(model.compute_dtype),
        "allowed_others": allowed, "others_before": wait_for_quiet(allowed, args.max_wait),
        "load_average_start": os.getloadavg(),
    }  # fmt: skip
    keyframes = args.pi3_keyframes if family == "pi3" else args.keyframes
    group["rows"] = time_group(model, keyframes, args, allowed)
    group["map"] = time_mapping(model, family, args, allowed)
    group["load_average_end"] = os.getloadavg()
    return group


def put_group(groups: list[dict[str, Any]], group: dict[str, Any]) -> None:
    """Replace the group of the same model, dtype and threads in ``groups``, or append it."""
    key = (group["model"], group["dtype"], group["threads"])
    same = [i for i, g in enumerate(groups) if (g["model"], g["dtype"], g["threads"]) == key]
    if same:
        groups[same[0]] = group
    else:
        groups.append(group)


def target_checks(result: dict[str, Any]) -> list[dict[str, Any]]:
    """``TARGET`` (best wall seconds of the step) checked for every thread count measured."""
    checks = []
    for group in result["groups"]:
        if (group["model"], group["dtype"]) != (TARGET["model"], TARGET["dtype"]):
            continue
        rows = [r for r in group["rows"] if r["keyframes"] == TARGET["keyframes"]]
        found = best(rows[0]["track_camera"] if rows else None, "wall", group["allowed_others"])
        if found is not None:
            met = found[0] <= TARGET["seconds"]
            checks.append({**TARGET, "threads": group["threads"], "measured": found[0],
                           "clean": found[1], "met": met})  # fmt: skip
    return checks


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the benchmark; print the tables, write the JSON; return the JSON content."""
    args = parse_args(argv)
    result: dict[str, Any] = {
        "resolution": [args.size, args.size], "pi3_size": args.pi3_size, "da3_size": args.da3_size,
        "clock": args.clock, "keyframes": args.keyframes,
        "headline_keyframes": args.headline_keyframes, "map_keyframes": args.map_keyframes,
        "warmup": args.warmup, "repeats": args.repeats, "budget_seconds": args.budget,
        "max_others": args.max_others, "threads": args.threads,
        "load_average_start": os.getloadavg(),
        "machine": {"cpus": os.cpu_count(), "processor": platform.processor(),
                    "platform": platform.platform(), "torch": torch.__version__,
                    "cpu_capability": torch.backends.cpu.get_cpu_capability(),
                    "python": platform.python_version()},
        "groups": [],
    }  # fmt: skip
    args.out_dir.mkdir(parents=True, exist_ok=True)
    json_path = args.out_dir / f"{args.name}.json"
    if args.update and json_path.exists():
        result["groups"] = json.loads(json_path.read_text())["groups"]
    for name in args.models:
        for dtype in args.dtypes:
            model = build_model(name, DTYPES[dtype])
            for threads in args.threads:
                group = run_group(model, name, dtype, threads, args)
                put_group(result["groups"], group)
                print(f"{name} {dtype} {threads} thread(s) done, load average "
                      f"{group['load_average_end']}", flush=True)  # fmt: skip
                # rewritten after every group: a long run that is stopped keeps what it measured
                result["load_average_end"] = os.getloadavg()
                json_path.write_text(json.dumps(result, indent=2) + "\n")
            del model  # the next one's weights replace these (Pi3 large: 3.8 GB in fp32)
    result["threads"] = sorted({g["threads"] for g in result["groups"]}, reverse=True)
    result["targets"] = target_checks(result)
    json_path.write_text(json.dumps(result, indent=2) + "\n")
    for threads in result["threads"]:
        for clock in dict.fromkeys((args.clock, "cpu")):
            print(f"\ntracking step in seconds (best-of {clock}), {threads} "
                  f"thread(s); camera head unless noted; * = every sample contended\n")  # fmt: skip
            print(markdown_table(result, threads, clock))
    for check in result["targets"]:
        verdict = "met" if check["met"] else "NOT met"
        print(f"\ntarget: {check['model']} {check['dtype']} step at N={check['keyframes']} <= "
              f"{check['seconds']} s, {check['threads']} thread(s): {check['measured']:.3f} s, "
              f"{verdict}")  # fmt: skip
    print(f"wrote {json_path}")
    return result


if __name__ == "__main__":
    main()

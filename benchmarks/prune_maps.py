"""Pruned maps and incremental keyframes: size, step time, insertion time,
and an accuracy proxy.

Two parts, both printed as Markdown tables and written to ``benchmarks/results/<--name>.json``:

``speed`` (random weights: the work does not depend on the values) — for Pi3 ``mid`` at 308 px
and DA3-Small at 224 px in bf16, N keyframes: the cache bytes, the map file's tensor bytes and the
tracking step (camera head) with every token (today's bf16 step), with 75 / 50 / 25 % kept, and
with 50 / 25 % kept in int8 (``cache.to(storage="int8")``, the quantised storage).
The variants take turns inside each round, so their ratios come from the same run under the same
load; the table gives medians. Then, at ``--insert-keyframes`` N (Pi3 ``mid``): a full rebuild
(the mapping pass over N+1 frames) against an incremental insertion (copy of the cache, one
tracking pass with every head, adopting its K/V).

``object``: Pi3 ``mid`` with every token against an object-mode cache (keyframes showing a
centred box of ``--object-area`` of the frame, mask dilated by one patch), in turns.

``accuracy`` (the golden Pi3 / DA3 weights over the 20 real TUM frames; random small weights, so
this is a proxy: the cost on real weights is unmeasured until someone runs it with them) — map
the even frames (10 keyframes) and track the odd ones; report how far poses and points move from
the fp32 map: bf16 (map and track in the SDK's bf16), pruned fp32 and bf16 caches (each pruning
score of ``cache/pruning.py``), and incremental
keyframes (a 2-keyframe map plus 8 insertions, against the rebuilt 10-keyframe map). A variant's
map is aligned to the reference map the way the tracker aligns a rebuild (Sim(3) from the shared
keyframes, scale from depths); translations are reported relative to the reference trajectory's
extent.

Run from the repository root::

    python -m benchmarks.prune_maps --part speed --keyframes 8 32 64
    python -m benchmarks.prune_maps --part accuracy
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.cache.pruning import PRUNE_SCORES, prune_cache
from kvtracker_sdk.io.map_file.map_schema import tensor_schema
from kvtracker_sdk.models.registry import family_of
from kvtracker_sdk.types import HeadSet

RESULTS = Path(__file__).parent / "results"
RATIOS = (1.0, 0.75, 0.5, 0.25)


def _label(ratio: float) -> str:
    return "all tokens" if ratio == 1.0 else f"{round(ratio * 100)} % kept"


# ---------------------------------------------------------------------------- speed
def _speed_model(name: str) -> tuple[Any, tuple[int, int]]:
    from benchmarks.tracking_vs_recompute import PRESETS
    from kvtracker_sdk.models.da3 import DA3Config, DepthAnything3
    from kvtracker_sdk.models.pi3 import Pi3

    torch.manual_seed(0)
    if name == "pi3-mid":
        model: Any = Pi3(PRESETS["mid"]())
        size = (308, 308)
    else:
        model = DepthAnything3(DA3Config.small())
        size = (224, 224)
    model = model.eval().requires_grad_(False)
    model.set_precision(torch.bfloat16)
    return model, size


def _random_cache(model: Any, keyframes: int, tokens: int) -> KVCache:
    """A bf16 cache of random K/V (every layer its own block, so pruning picks per layer)."""
    layout = family_of(model).cache_layout(model)
    shape = (1, layout.num_heads, keyframes * tokens, layout.head_dim)
    g = torch.Generator().manual_seed(keyframes)
    keys = [torch.randn(shape, generator=g, dtype=torch.bfloat16) for _ in range(layout.num_layers)]
    return KVCache.from_layers(
        keys, keys, layout=layout, tokens_per_frame=tokens, keyframe_ids=range(keyframes)
    )


def _file_bytes(cache: KVCache, size: tuple[int, int]) -> int:
    """Bytes of a map file's tensors for ``cache`` (the JSON header, a few kB, excluded)."""
    lengths = (
        tuple(cache.layer_length(i) for i in range(cache.layout.num_layers))
        if cache.pruned
        else None
    )
    schema = tensor_schema(
        cache.layout, cache.storage, cache.num_keyframes, cache.tokens_per_frame, size, lengths
    )
    return sum(spec.nbytes for spec in schema.values())


def _timed(fn: Callable[[], object]) -> dict[str, float]:
    wall, cpu = time.perf_counter(), time.process_time()
    fn()
    return {"wall": time.perf_counter() - wall, "cpu": time.process_time() - cpu}


def _median(samples: list[dict[str, float]]) -> dict[str, float]:
    return {c: statistics.median(s[c] for s in samples) for c in ("wall", "cpu")}


# speed variants: (keep ratio, storage at rest); None = bf16 dense
SPEED_VARIANTS: tuple[tuple[float, str | None], ...] = (
    *((ratio, None) for ratio in RATIOS), (0.5, "int8"), (0.25, "int8"),
)


def _variant_label(ratio: float, storage: str | None) -> str:
    return _label(ratio) + ("" if storage is None else f" + {storage}")


@torch.no_grad()
def speed_rows(name: str, keyframes: int, args: argparse.Namespace) -> dict[str, Any]:
    model, size = _speed_model(name)
    extra = family_of(model).extra_tokens_per_frame(model)
    tokens = model.tokens_per_frame(*size)
    caches = {}
    for ratio, storage in SPEED_VARIANTS:
        cache = _random_cache(model, keyframes, tokens)
        if ratio < 1.0:
            prune_cache(cache, keep_ratio=ratio, extra_tokens_per_frame=extra)
        caches[(ratio, storage)] = cache if storage is None else cache.to(storage=storage)
    query = torch.rand(1, 3, *size, generator=torch.Generator().manual_seed(0))
    samples: dict[tuple[float, str | None], list[dict[str, float]]] = {v: [] for v in caches}
    load_start = os.getloadavg()
    for round_index in range(args.warmup + args.rounds):
        order = list(caches) if round_index % 2 == 0 else list(reversed(caches))
        for variant in order:
            timing = _timed(lambda: model.forward_track(query, caches[variant], heads=HeadSet.CAMERA))  # noqa: B023
            if round_index >= args.warmup:
                samples[variant].append(timing)
    load_end = os.getloadavg()
    base = _median(samples[(1.0, None)])
    rows = []
    for (ratio, storage), cache in caches.items():
        step = _median(samples[(ratio, storage)])
        rows.append({
            "keep_ratio": ratio,
            "storage": storage or "bfloat16",
            "label": _variant_label(ratio, storage),
            "cache_bytes": cache.nbytes,
            "cache_ratio_vs_all": caches[(1.0, None)].nbytes / cache.nbytes,
            "file_tensor_bytes": _file_bytes(cache, size),
            "step_median": step,
            "speedup_vs_all": {c: base[c] / step[c] for c in step},
            "samples": samples[(ratio, storage)],
        })  # fmt: skip
    return {
        "model": name, "size": list(size), "keyframes": keyframes, "tokens_per_frame": tokens,
        "rows": rows, "loadavg_start": load_start, "loadavg_end": load_end,
    }  # fmt: skip


@torch.no_grad()
def object_rows(keyframes: int, area: float, args: argparse.Namespace) -> dict[str, Any]:
    """Pi3 ``mid``: the step against every token vs against an object-mode cache whose keyframes
    show a centred box of ``area`` of the frame (dilated by one patch), in turns."""
    from kvtracker_sdk.cache.pruning import object_token_mask

    model, size = _speed_model("pi3-mid")
    extra = family_of(model).extra_tokens_per_frame(model)
    tokens = model.tokens_per_frame(*size)
    mask = np.zeros(size, dtype=bool)
    side = (np.sqrt(area) * np.array(size)).astype(int)
    top, left = (np.array(size) - side) // 2
    mask[top : top + side[0], left : left + side[1]] = True
    allowed = object_token_mask([mask] * keyframes, patch_size=14, extra_tokens_per_frame=extra)
    caches = {"all tokens": _random_cache(model, keyframes, tokens)}
    caches["object"] = _random_cache(model, keyframes, tokens)
    prune_cache(caches["object"], keep_ratio=1.0, extra_tokens_per_frame=extra, allowed=allowed)
    query = torch.rand(1, 3, *size, generator=torch.Generator().manual_seed(0))
    samples: dict[str, list[dict[str, float]]] = {k: [] for k in caches}
    load_start = os.getloadavg()
    for round_index in range(args.warmup + args.rounds):
        for name in caches if round_index % 2 == 0 else reversed(list(caches)):
            timing = _timed(lambda: model.forward_track(query, caches[name], heads=HeadSet.CAMERA))  # noqa: B023
            if round_index >= args.warmup:
                samples[name].append(timing)
    steps = {name: _median(s) for name, s in samples.items()}
    return {
        "model": "pi3-mid", "size": list(size), "keyframes": keyframes, "object_area": area,
        "kept_fraction": caches["object"].layer_length(0) / (keyframes * tokens),
        "cache_bytes": {k: c.nbytes for k, c in caches.items()}, "step_median": steps,
        "speedup": {c: steps["all tokens"][c] / steps["object"][c] for c in ("wall", "cpu")},
        "samples": samples, "loadavg_start": load_start, "loadavg_end": os.getloadavg(),
    }  # fmt: skip


@torch.no_grad()
def insertion_vs_rebuild(keyframes: int, args: argparse.Namespace) -> dict[str, Any]:
    model, size = _speed_model("pi3-mid")
    family = family_of(model)
    frames = torch.rand(keyframes + 1, 3, *size, generator=torch.Generator().manual_seed(1))
    load_start = os.getloadavg()

    def rebuild() -> None:
        mapped = family.map(model, frames)
        KVCache.from_layers(
            mapped.keys, mapped.values, layout=family.cache_layout(model),
            tokens_per_frame=mapped.tokens_per_frame, keyframe_ids=range(keyframes + 1),
        )  # fmt: skip

    rebuild_timing = _timed(rebuild)  # one run: tens of seconds
    cache = _random_cache(model, keyframes, model.tokens_per_frame(*size))

    def insert() -> None:
        copy = cache.clone()
        with copy.lock:
            model.forward_track(frames[-1:], copy, heads=HeadSet.ALL)
            copy.adopt_scratch(keyframes)

    inserts = [_timed(insert) for _ in range(args.warmup + args.rounds)][args.warmup :]
    insertion = _median(inserts)
    return {
        "model": "pi3-mid", "size": list(size), "keyframes": keyframes,
        "rebuild": rebuild_timing, "insertion_median": insertion, "insertion_samples": inserts,
        "insertion_over_rebuild": {c: insertion[c] / rebuild_timing[c] for c in insertion},
        "loadavg_start": load_start, "loadavg_end": os.getloadavg(),
    }  # fmt: skip


def speed_table(results: list[dict[str, Any]], clock: str) -> str:
    lines = [
        f"| model | N | tokens kept | cache MB | file MB | step (s, {clock}, median) "
        "| speed-up vs all tokens | load avg (start → end) |",
        "|---|---:|---|---:|---:|---:|---:|---|",
    ]
    for result in results:
        for row in result["rows"]:
            lines.append(
                f"| {result['model']} {result['size'][0]} | {result['keyframes']} "
                f"| {row['label']} | {row['cache_bytes'] / 1e6:.1f} "
                f"| {row['file_tensor_bytes'] / 1e6:.1f} | {row['step_median'][clock]:.3f} "
                f"| {row['speedup_vs_all'][clock]:.2f}× "
                f"| {result['loadavg_start'][0]:.2f} → {result['loadavg_end'][0]:.2f} |"
            )
    return "\n".join(lines)


# ---------------------------------------------------------------------------- accuracy
def _tum_frames(family: str, resolution: int) -> np.ndarray:
    import cv2

    from kvtracker_sdk.preprocess.families import for_family

    folder = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "tum_fr2_desk"
    files = sorted((folder / "rgb").glob("*.png"))[:20]
    prep = for_family(family)
    images = [cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB) for f in files]
    return np.stack([prep.resize(image, resolution, 14).image for image in images])


def _weights(family: str) -> Path:
    root = Path(__file__).resolve().parent.parent.parent / "shared" / "golden"
    return root / family / "weights.safetensors"


@dataclass(frozen=True)
class _Run:
    """A map (its keyframes' raw poses and points: what aligns it) and the compared poses and
    points (frames tracked against it, or keyframes)."""

    kf_poses: np.ndarray
    kf_points: np.ndarray
    poses: np.ndarray
    points: np.ndarray


def _tracked(backend: Any, cache: KVCache, images: np.ndarray, kf_poses: Any, kf_points: Any) -> _Run:
    tracked = [backend.track(image, cache, heads=HeadSet.ALL) for image in images]
    return _Run(
        np.asarray(kf_poses), np.asarray(kf_points),
        np.stack([t.pose for t in tracked]), np.stack([t.local_points for t in tracked]),
    )  # fmt: skip


def _deviation(reference: _Run, run: _Run) -> dict[str, float]:
    """Pose and point deviation of ``run`` from ``reference`` after the tracker's alignment
    (Sim(3) from the shared keyframes, scale from their depths)."""
    from kvtracker_sdk.geometry.se3 import invert_rigid
    from kvtracker_sdk.tracking.core.gauge import anchor_gauge, depth_scale, estimate_gauge

    ref_gauge = anchor_gauge(reference.kf_poses[0])
    ref_world = ref_gauge.apply_to_pose(reference.kf_poses)
    scale = depth_scale(list(reference.kf_points), list(run.kf_points), [None] * len(run.kf_points))
    gauge = estimate_gauge(ref_world, run.kf_poses, scale)
    ref_tracked = ref_gauge.apply_to_pose(reference.poses)
    tracked = gauge.apply_to_pose(run.poses)
    extent = float(np.linalg.norm(ref_world[:, :3, 3], axis=1).max())
    rotation = [
        float(np.degrees(np.arccos(np.clip((np.trace(invert_rigid(a) @ b) - 2.0) / 2.0, -1, 1))))
        for a, b in zip(ref_tracked, tracked, strict=True)
    ]
    translation = np.linalg.norm(ref_tracked[:, :3, 3] - tracked[:, :3, 3], axis=1) / extent
    points = np.linalg.norm(run.points * gauge.scale - reference.points, axis=-1) / np.maximum(
        np.linalg.norm(reference.points, axis=-1), 1e-9
    )
    return {
        "rotation_deg_median": float(np.median(rotation)),
        "rotation_deg_max": float(np.max(rotation)),
        "translation_rel_median": float(np.median(translation)),
        "translation_rel_max": float(np.max(translation)),
        "points_rel_median": float(np.median(points)),
    }


@torch.no_grad()
def accuracy(family: str, resolution: int) -> dict[str, Any]:
    from kvtracker_sdk.backends.torch_backend import TorchBackend

    torch.manual_seed(0)
    images = _tum_frames(family, resolution)
    keyframes, queries = images[0::2], images[1::2]
    fp32 = TorchBackend.from_pretrained(_weights(family))
    extra = fp32.info.extra_tokens_per_frame
    mapped = fp32.map(keyframes)
    reference = _tracked(fp32, mapped.cache, queries, mapped.poses, mapped.local_points)
    variants: dict[str, dict[str, Any]] = {}

    bf16 = TorchBackend.from_pretrained(_weights(family), dtype=torch.bfloat16)
    bf16_map = bf16.map(keyframes)
    bf16_run = _tracked(bf16, bf16_map.cache, queries, bf16_map.poses, bf16_map.local_points)
    variants["bf16 (map and track)"] = {
        **_deviation(reference, bf16_run), "cache_bytes": bf16_map.cache.nbytes,
    }  # fmt: skip
    for score in PRUNE_SCORES:
        for ratio in RATIOS[1:]:
            for name, backend, base in (("fp32", fp32, mapped), ("bf16", bf16, bf16_map)):
                cache = base.cache.clone()
                prune_cache(cache, keep_ratio=ratio, extra_tokens_per_frame=extra, score=score)
                run = _tracked(backend, cache, queries, base.poses, base.local_points)
                variants[f"{name}, {_label(ratio)}, {score}"] = {
                    **_deviation(reference, run), "cache_bytes": cache.nbytes,
                }  # fmt: skip

    # incremental: keyframes 0 and 1 mapped, 8 inserted; against the rebuilt 10-keyframe map
    small = fp32.map(keyframes[:2])
    cache, poses, points = small.cache, list(small.poses), list(small.local_points)
    insert_ms = []
    for index, image in enumerate(keyframes[2:], start=2):
        start = time.perf_counter()
        with cache.lock:
            inserted = fp32.track(image, cache, heads=HeadSet.ALL)
            cache.adopt_scratch(index)
        insert_ms.append((time.perf_counter() - start) * 1e3)
        poses.append(inserted.pose)
        points.append(inserted.local_points)
    kf_poses, kf_points = np.stack(poses), np.stack(points)
    incremental = _tracked(fp32, cache, queries, kf_poses, kf_points)
    inserted_kf = _Run(kf_poses, kf_points, kf_poses[2:], kf_points[2:])
    rebuilt_kf = _Run(mapped.poses, mapped.local_points, mapped.poses[2:], mapped.local_points[2:])
    variants["incremental (2 mapped + 8 inserted), tracked frames"] = {
        **_deviation(reference, incremental), "cache_bytes": cache.nbytes,
        "insert_ms_median": statistics.median(insert_ms),
    }  # fmt: skip
    variants["incremental, the 8 inserted keyframes' poses"] = _deviation(rebuilt_kf, inserted_kf)
    return {
        "family": family, "resolution": list(images.shape[1:3]), "keyframes": len(keyframes),
        "queries": len(queries), "reference_cache_bytes": mapped.cache.nbytes,
        "variants": variants, "loadavg": os.getloadavg(),
    }  # fmt: skip


def accuracy_table(results: list[dict[str, Any]]) -> str:
    lines = [
        "| model | variant | cache MB | rotation ° (median / max) | translation / extent "
        "(median / max) | points rel. (median) |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for result in results:
        for name, dev in result["variants"].items():
            size = f"{dev['cache_bytes'] / 1e6:.2f}" if "cache_bytes" in dev else "–"
            lines.append(
                f"| {result['family']} {result['resolution'][0]}×{result['resolution'][1]} "
                f"| {name} | {size} "
                f"| {dev['rotation_deg_median']:.3g} / {dev['rotation_deg_max']:.3g} "
                f"| {dev['translation_rel_median']:.3g} / {dev['translation_rel_max']:.3g} "
                f"| {dev['points_rel_median']:.3g} |"
            )
    return "\n".join(lines)


# ---------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--part", choices=("speed", "object", "accuracy", "insertion"), required=True
    )
    parser.add_argument("--object-area", type=float, default=0.25, help="box area / frame area")
    parser.add_argument("--models", nargs="+", default=["pi3-mid", "da3-small"])
    parser.add_argument("--keyframes", nargs="+", type=int, default=[8, 32, 64])
    parser.add_argument("--insert-keyframes", type=int, default=32)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--clock", choices=("wall", "cpu"), default="cpu")
    parser.add_argument("--name", help="output file stem (default prune_maps_<part>)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    result: dict[str, Any] = {
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "threads": args.threads, "clock": args.clock,
    }  # fmt: skip
    if args.part == "speed":
        rows = [speed_rows(m, n, args) for m in args.models for n in args.keyframes]
        result["speed"] = rows
        print(speed_table(rows, args.clock))
    elif args.part == "object":
        rows = [object_rows(n, args.object_area, args) for n in args.keyframes]
        result["object"] = rows
        for row in rows:
            print(
                f"pi3-mid 308, N={row['keyframes']}, object box {row['object_area']:.0%} of the "
                f"frame: {row['kept_fraction']:.0%} of the tokens kept, cache "
                f"{row['cache_bytes']['all tokens'] / 1e6:.0f} -> {row['cache_bytes']['object'] / 1e6:.0f} MB, "
                f"step {row['step_median']['all tokens'][args.clock]:.3f} -> "
                f"{row['step_median']['object'][args.clock]:.3f} s "
                f"({row['speedup'][args.clock]:.2f}x), load "
                f"{row['loadavg_start'][0]:.2f} -> {row['loadavg_end'][0]:.2f}"
            )
    elif args.part == "insertion":
        row = insertion_vs_rebuild(args.insert_keyframes, args)
        result["insertion"] = row
        print(
            f"pi3-mid 308, N={row['keyframes']}: rebuild {row['rebuild'][args.clock]:.2f} s, "
            f"insertion {row['insertion_median'][args.clock]:.3f} s "
            f"({row['insertion_over_rebuild'][args.clock]:.3f} of a rebuild), load "
            f"{row['loadavg_start'][0]:.2f} → {row['loadavg_end'][0]:.2f}"
        )
    else:
        rows = [accuracy("pi3", 224), accuracy("da3", 224)]
        result["accuracy"] = rows
        print(accuracy_table(rows))
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{args.name or 'prune_maps_' + args.part}.json"
    path.write_text(json.dumps(result, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

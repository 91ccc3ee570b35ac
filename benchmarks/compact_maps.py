"""Compact maps: size, tracking step and accuracy proxy of cache variants, side by side.

For each model (Pi3 ``mid`` at d = 308 and DA3-Small at d = 224, random weights: speed does not
depend on values; frames sized as the preprocessing sizes a 640x480 frame) and each number of
keyframes N, one random bf16 cache is made and every **variant** is derived from it:

- ``dense``: today's cache (bf16 K/V, the bf16 backend's);
- ``int8`` / ``fp8``: quantised at rest (``kvtracker_sdk/cache/quantization.py``), dequantised one
  layer at a time into a bf16 work pair while tracking; their map files store the keyframe
  payload compactly (``io/map_file/keyframe_codec.py``: mask bits, uint16 confidences, float16 points —
  DA3's as depth x rays);
- ``int8-full``: int8 K/V with the keyframe payload in full (format version 2, as before
  version 3), to show what the compact payload adds.

Per (model, N, variant): the ``.kvmap`` file's bytes (saved for real, then deleted; keyframes
with random images and points shaped as the family makes them: DA3's are depth x pinhole rays),
the bytes per keyframe of each part of the file (K/V, image, mask, confidence, points, other),
the K/V bytes (file and cache), and the tracking step (bf16 model, camera head, 1 thread, process CPU
time): in each round every variant runs once, in rotating order, so all see the same load; the
table gives the median over rounds and the median of the per-round ratios to ``dense``.

The accuracy proxy (``kvtracker_sdk/eval/cache_deviation.py``) runs on the golden reduced Pi3 and
DA3 over the 20 real TUM frames (keyframes 0, 5, 10, 15; the 16 others tracked): each variant's
deviation from the fp32 model on its fp32 cache, with fp32 and with bf16 compute, next to the
``dense`` bf16 backend's. Random/reduced weights: the accuracy cost on real weights is unmeasured.

Other compactions plug in as variants: a :class:`Variant` has a ``storage`` and/or a
``transform`` (``KVCache -> KVCache``, e.g. pruning to a budget) and an optional ``measure``
hook returning extra numbers for its row (e.g. insertion time); ``--variants`` picks them.

``--files-only`` skips the steps and the accuracy table and adds the payload deviation: the
golden models map 4 TUM frames at d = 224 in fp32; their keyframe points and confidences go
through the compact payload and back, next to the points of the same frames mapped by the bf16
backend (the deviation users already accept), both relative to the fp32 points.

Run from the repository root::

    python -m benchmarks.compact_maps [--models pi3-mid da3-small] [--keyframes 8 32 64]
        [--rounds 3] [--skip-accuracy] [--files-only] [--name compact_maps]
        [--out-dir benchmarks/results]

Writes ``benchmarks/results/<name>.json`` and prints the tables with the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from benchmarks.compact_payload import PARTS, composition, keyframe_payload, payload_deviation
from benchmarks.model_families import MODELS as FAMILY_MODELS
from benchmarks.tracking_vs_recompute import PRESETS
from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.cache import CacheLayout, KeyframeMap, KVCache
from kvtracker_sdk.eval.cache_deviation import CacheVariant, cache_deviation, tum_frames
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.io.map_file.map_file import read_map_info, save_map
from kvtracker_sdk.io.sources.sources import TumSource
from kvtracker_sdk.models.da3 import DA3Config, DepthAnything3
from kvtracker_sdk.models.pi3 import Pi3
from kvtracker_sdk.models.registry import family_of
from kvtracker_sdk.types import HeadSet

RESULTS = Path(__file__).parent / "results"
SHARED = Path(__file__).resolve().parents[1].parent / "shared"


@dataclass(frozen=True)
class Variant:
    """One compaction of a map's cache (see the module docstring)."""

    name: str
    storage: str | None = None
    transform: Callable[[KVCache], KVCache] | None = None
    measure: Callable[[Setup, KVCache], dict[str, float]] | None = None
    compact_keyframes: bool | None = None  # save_map's (None: compact iff quantised)

    def apply(self, cache: KVCache) -> KVCache:
        out = cache.to(storage=self.storage) if self.storage is not None else cache
        return self.transform(out) if self.transform is not None else out


VARIANTS: dict[str, Variant] = {
    "dense": Variant("dense"),
    "int8": Variant("int8", storage="int8"),
    "fp8": Variant("fp8", storage="fp8"),
    "int8-full": Variant("int8-full", storage="int8", compact_keyframes=False),
}


@dataclass(frozen=True)
class ModelSpec:
    name: str
    build: Callable[[], nn.Module]
    size: tuple[int, int]  # (H, W) of a 640x480 frame after the family's preprocessing


MODELS: dict[str, ModelSpec] = {
    # d = 308 and d = 224: a 640x480 frame as the tracker prepares it
    "pi3-mid": ModelSpec("pi3-mid", lambda: Pi3(PRESETS["mid"]()), (266, 350)),
    "da3-small": ModelSpec("da3-small", lambda: DepthAnything3(DA3Config.small()), (168, 224)),
    # the smoke test's
    "pi3-tiny": ModelSpec("pi3-tiny", FAMILY_MODELS["pi3-tiny"][0], (56, 56)),
    "da3-tiny": ModelSpec("da3-tiny", FAMILY_MODELS["da3-tiny"][0], (42, 70)),
}


@dataclass
class Setup:
    """A model in bf16, its backend description and one query frame."""

    spec: ModelSpec
    model: Any
    backend: TorchBackend
    layout: CacheLayout
    tokens: int
    query: torch.Tensor = field(repr=False)


def make_setup(spec: ModelSpec) -> Setup:
    torch.manual_seed(0)
    model = spec.build().eval().requires_grad_(False)
    model.set_precision(torch.bfloat16)
    backend = TorchBackend(model, dtype=torch.bfloat16, weights_fingerprint=f"random-{spec.name}")
    layout = family_of(model).cache_layout(model)
    height, width = spec.size
    query = torch.rand(1, 3, height, width, generator=torch.Generator().manual_seed(0))
    return Setup(spec, model, backend, layout, model.tokens_per_frame(height, width), query)


def random_cache(setup: Setup, keyframes: int) -> KVCache:
    """Random bf16 K/V of ``keyframes`` frames (one block shared by the layers: values do not
    change the work; quantisation of each layer still runs)."""
    layout = setup.layout
    shape = (1, layout.num_heads, keyframes * setup.tokens, layout.head_dim)
    block = torch.randn(shape, generator=torch.Generator().manual_seed(keyframes))
    layers = [block.to(torch.bfloat16)] * layout.num_layers
    return KVCache.from_layers(layers, layers, layout=layout, tokens_per_frame=setup.tokens,
                               keyframe_ids=range(keyframes))  # fmt: skip


def file_bytes(
    setup: Setup, cache: KVCache, folder: Path, compact_keyframes: bool | None = None
) -> tuple[int, int, str, dict[str, float]]:
    """(file bytes, K/V bytes in the header, keyframe encoding, bytes per keyframe by part) of
    the map of ``cache`` with :func:`keyframe_payload` keyframes."""
    keyframes = tuple(keyframe_payload(setup.spec.name, setup.spec.size, cache.num_keyframes))
    keyframe_map = KeyframeMap(keyframes, cache, Sim3.identity(), generation=1,
                               resolution=setup.spec.size)  # fmt: skip
    path = folder / "bench.kvmap"
    try:
        save_map(path, keyframe_map, backend_info=setup.backend.info, tracker_config_json="{}",
                 mode="scene", compact_keyframes=compact_keyframes)  # fmt: skip
        info = read_map_info(path)
        return path.stat().st_size, info.cache_nbytes, info.keyframe_encoding, composition(info)
    finally:
        path.unlink(missing_ok=True)


def step_cpu_seconds(setup: Setup, cache: KVCache) -> float:
    """Process CPU seconds of one tracking step (camera head)."""
    start = time.process_time()
    with torch.no_grad():
        setup.model.forward_track(setup.query, cache, heads=HeadSet.CAMERA)
    return time.process_time() - start


def run_point(
    setup: Setup, keyframes: int, variants: Sequence[Variant], rounds: int, folder: Path,
    *, steps: bool = True,
) -> list[dict[str, Any]]:
    """Every variant at N = ``keyframes``: sizes, then ``rounds`` rotating rounds of steps
    (none without ``steps``)."""
    base = random_cache(setup, keyframes)
    caches = {v.name: v.apply(base) for v in variants}
    rows: dict[str, dict[str, Any]] = {}
    for variant in variants:
        cache = caches[variant.name]
        size, kv_bytes, encoding, parts = file_bytes(setup, cache, folder, variant.compact_keyframes)
        rows[variant.name] = {
            "model": setup.spec.name, "size_hw": list(setup.spec.size), "keyframes": keyframes,
            "variant": variant.name, "storage": cache.storage, "file_bytes": size,
            "file_kv_bytes": kv_bytes, "keyframe_encoding": encoding,
            "file_bytes_per_keyframe": parts, "cache_bytes": cache.nbytes,
            "cache_allocated_bytes": cache.allocated_nbytes, "step_cpu_s": [],
        }  # fmt: skip
        if variant.measure is not None:
            rows[variant.name].update(variant.measure(setup, cache))
        if steps:
            step_cpu_seconds(setup, cache)  # warm-up
    for round_index in range(rounds if steps else 0):
        shift = round_index % len(variants)
        for variant in [*variants[shift:], *variants[:shift]]:
            rows[variant.name]["step_cpu_s"].append(step_cpu_seconds(setup, caches[variant.name]))
    reference = rows[variants[0].name]
    for row in rows.values():
        if steps:
            row["step_cpu_median_s"] = statistics.median(row["step_cpu_s"])
            ratios = [a / b for a, b in zip(row["step_cpu_s"], reference["step_cpu_s"], strict=True)]
            row["step_ratio_median"] = statistics.median(ratios)
        row["file_ratio"] = reference["file_bytes"] / row["file_bytes"]
        row["kv_ratio"] = reference["cache_bytes"] / row["cache_bytes"]
    return list(rows.values())


def accuracy(variants: Sequence[Variant]) -> list[dict[str, Any]]:
    """Deviation rows on the golden models (fp32 and bf16 compute for each variant)."""
    frames_source = list(TumSource(SHARED / "data" / "tum_fr2_desk"))
    rows: list[dict[str, Any]] = []
    for family in ("pi3", "da3"):
        frames = tum_frames(frames_source, family, resolution=224)
        cache_variants = [
            CacheVariant(f"{v.name}/{dtype}", dtype=dtype, storage=v.storage, transform=v.transform)
            for v in variants
            for dtype in ("float32", "bfloat16")
            if not (v.storage is None and v.transform is None and dtype == "float32")  # = reference
        ]
        weights = SHARED / "golden" / family / "weights.safetensors"
        for deviation in cache_deviation(weights, frames, [0, 5, 10, 15], cache_variants):
            rows.append({"model": f"golden-{family}", **deviation.to_dict()})
    return rows


def print_tables(result: dict[str, Any]) -> None:
    print(f"\nload average {result['load_average_start']} -> {result['load_average_end']}, "
          f"{result['threads']} thread, process CPU time, median of {result['rounds']} rounds")  # fmt: skip
    print("\n| model, frame | N | variant | map file | ratio | K/V | ratio | step (s) | step ratio |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|")
    for row in result["rows"]:
        h, w = row["size_hw"]
        step = (f"{row['step_cpu_median_s']:.3f} | {row['step_ratio_median']:.2f}"
                if "step_cpu_median_s" in row else "– | –")  # fmt: skip
        print(f"| {row['model']}, {h}×{w} | {row['keyframes']} | {row['variant']} | "
              f"{row['file_bytes'] / 1e6:.1f} MB | {row['file_ratio']:.2f}× | "
              f"{row['cache_bytes'] / 1e6:.1f} MB | {row['kv_ratio']:.2f}× | {step} |")  # fmt: skip
    print("\n| model | N | variant | keyframe encoding | kB per keyframe: " + " | ".join(PARTS)
          + " | other |")  # fmt: skip
    print("|---|---:|---|---|" + "---:|" * (len(PARTS) + 1))
    for row in result["rows"]:
        parts = " | ".join(f"{v / 1e3:.0f}" for v in row["file_bytes_per_keyframe"].values())
        print(f"| {row['model']} | {row['keyframes']} | {row['variant']} | "
              f"{row['keyframe_encoding']} | {parts} |")  # fmt: skip
    if result.get("payload"):
        print("\n| golden model | encoding | points rel. median / max: compact | bf16 backend | "
              "confidence |Δ| max: compact | bf16 backend |")
        print("|---|---|---|---|---:|---:|")
        for row in result["payload"]:
            print(f"| {row['model']} | {row['encoding']} | {row['compact_points_rel_median']:.1e} / "
                  f"{row['compact_points_rel_max']:.1e} | {row['bf16_points_rel_median']:.1e} / "
                  f"{row['bf16_points_rel_max']:.1e} | {row['compact_confidence_abs_max']:.1e} | "
                  f"{row['bf16_confidence_abs_max']:.1e} |")  # fmt: skip
    if result["accuracy"]:
        print("\n| golden model | variant/compute | K/V | pose max | pose median | rot max (°) | points median |")
        print("|---|---|---:|---:|---:|---:|---:|")
        for row in result["accuracy"]:
            print(f"| {row['model']} | {row['variant']} | {row['cache_bytes'] / 1e6:.2f} MB | "
                  f"{row['pose_max']:.1e} | {row['pose_median']:.1e} | "
                  f"{row['rotation_deg_max']:.3f} | {row['points_median']:.1e} |")  # fmt: skip


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--models", nargs="+", choices=sorted(MODELS), default=["pi3-mid", "da3-small"])
    parser.add_argument("--keyframes", nargs="+", type=int, default=[8, 32, 64])
    parser.add_argument("--variants", nargs="+", choices=sorted(VARIANTS), default=list(VARIANTS))
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--skip-accuracy", action="store_true")
    parser.add_argument("--files-only", action="store_true",
                        help="map file sizes and the payload deviation; no steps, no accuracy")  # fmt: skip
    parser.add_argument("--name", default="compact_maps")
    parser.add_argument("--out-dir", type=Path, default=RESULTS)
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.set_flush_denormal(True)  # random weights make denormals, which slow CPU kernels
    try:
        return run(args)
    finally:  # process-wide state: a caller (the smoke test's pytest process) gets it back
        torch.set_flush_denormal(False)


def run(args: argparse.Namespace) -> dict[str, Any]:
    variants = [VARIANTS[name] for name in args.variants]
    if variants[0].name != "dense":
        variants.insert(0, VARIANTS["dense"])  # the ratios' reference
    result: dict[str, Any] = {
        "machine": platform.processor() or platform.machine(), "torch": torch.__version__,
        "threads": args.threads, "rounds": args.rounds,
        "load_average_start": [round(x, 2) for x in os.getloadavg()], "rows": [], "accuracy": [],
    }  # fmt: skip
    with tempfile.TemporaryDirectory() as folder:
        for name in args.models:
            setup = make_setup(MODELS[name])
            for keyframes in args.keyframes:
                rows = run_point(setup, keyframes, variants, args.rounds, Path(folder),
                                 steps=not args.files_only)  # fmt: skip
                result["rows"].extend(rows)
                print(f"{name} N={keyframes}: " + ", ".join(
                    f"{r['variant']} {r['file_ratio']:.2f}x" for r in rows), flush=True)  # fmt: skip
            del setup
    if args.files_only:
        result["payload"] = payload_deviation(SHARED)
    elif not args.skip_accuracy:
        result["accuracy"] = accuracy(variants)
    result["load_average_end"] = [round(x, 2) for x in os.getloadavg()]
    args.out_dir.mkdir(parents=True, exist_ok=True)
    (args.out_dir / f"{args.name}.json").write_text(json.dumps(result, indent=1))
    print_tables(result)
    return result


if __name__ == "__main__":
    main()

"""Every CPU runtime of the tracking step side by side, with its FLOPs and the machine's GEMM peak.

For each model (``--models``: Pi3 ``large``, DA3-Small / -Base; random weights, the work does not
depend on them), frame size (``--sizes``, squares), keyframe count N (``--keyframes``) and head set
(``--heads``: ``camera``, ``conf`` = with confidence), one query frame is tracked against a random
cache of N keyframes by each variant (``--variants``):

- ``torch-fp32`` / ``torch-bf16``: the SDK's eager step (``family.track``: model + conversion);
- ``compile-bf16`` / ``compile-fp32``: the same step through ``torch.compile`` (Inductor, freezing;
  ``backends/torch_compile.py``); the first call (compile + one step) is reported apart;
- ``official-bf16`` / ``official-fp32``: the official code's step: fp32 weights, each global layer
  concatenates the cache with the frame's K/V (``torch.cat``) and calls SDPA, under
  ``torch.autocast(bfloat16)`` for bf16 (what the official Pi3/DA3 code runs);
- ``onnx-fp32``: ``OnnxBackend`` over an export of the same weights (``--onnx-dir``; exported once);
- ``openvino-bf16`` / ``openvino-fp32``: ``OpenVinoBackend`` over that export with the precision
  hint and its default static shapes (every tracking graph in fp32, the encoder in bf16), when
  the SDK has it and ``openvino`` imports (else the variant is reported as skipped);
  ``openvino-static-bf16``: every tracking graph static (``static_shapes=True``);
  ``openvino-dynamic-bf16`` / ``-fp32``: the dynamic graphs (``static_shapes=False``). The
  static compiles are part of the first call.

All variants of a point take turns in every round (rotating order), with two GEMM probes, a bf16
and an fp32 ``[1024 x 1024] x [1024 x 4096]`` product: the **peak matrix-product rate measured in
the same run**. Each step's FLOPs are counted on the eager fp32 step (``torch.utils.flop_counter``;
CPU flash attention counted as its two products), so ``limit = FLOPs / peak(dtype)`` and
``fraction of the limit = limit / best time``. The pose deviation is the largest absolute
difference of the 4x4 ``T_world_cam`` from ``torch-fp32`` (the bf16 caches hold the fp32 cache's
values, rounded). Only ratios measured in one run are figures on a shared machine: the JSON
keeps every sample, the cores other processes used per round and the load averages.

Run from the repository root (``--threads 1 --clock cpu`` by default: one thread's process CPU
time repeats within a few % on a shared CPU)::

    python -m benchmarks.runtimes --models da3-small pi3-large --sizes 224 --keyframes 8
    python -m benchmarks.runtimes --models da3-small da3-base --sizes 224 308 --keyframes 1 8 32 \
        --heads camera conf

With ``--threads`` above 1 set ``OMP_WAIT_POLICY=PASSIVE`` in the environment: this script loads
torch before ``kvtracker_sdk`` could choose the policy, and spinning threads on a shared CPU make
wall times meaningless (a 2-thread trial here gave the official step a 0.31-1.1 s spread).
``--summary FILE`` re-prints a saved JSON's one-line-per-point summary.

Writes ``benchmarks/results/<--name>.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import statistics
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.flop_counter import FlopCounterMode, register_flop_formula

from benchmarks.model_families import MODELS, build_model, random_cache
from benchmarks.shared_cpu_timing import OtherLoad
from kvtracker_sdk.backends.torch_compile import CompiledTracking, CompileOptions
from kvtracker_sdk.cache import KVCache
from kvtracker_sdk.models.da3 import dpt_blocks, dualdpt
from kvtracker_sdk.models.layers.attention import Attention
from kvtracker_sdk.models.layers.cached_attention import use_cached_kernel
from kvtracker_sdk.models.registry import family_of
from kvtracker_sdk.types import HeadSet

RESULTS = Path(__file__).parent / "results"
HEADS = {"camera": HeadSet.CAMERA, "conf": HeadSet.CONFIDENCE}
# <kind>-<dtype>; "products": the cached attention as two bf16 products (cached_attention.py)
TORCH_VARIANTS = ("torch-fp32", "torch-bf16", "compile-bf16", "compile-fp32", "products-bf16",
                  "compile+products-bf16", "official-bf16", "official-fp32")  # fmt: skip
OPENVINO_VARIANTS = ("openvino-bf16", "openvino-fp32", "openvino-static-bf16",
                     "openvino-dynamic-bf16", "openvino-dynamic-fp32")  # fmt: skip
# variant -> OpenVinoBackend(static_shapes=...); the others: the default (None)
OPENVINO_STATIC = {"openvino-static-bf16": True, "openvino-dynamic-bf16": False,
                   "openvino-dynamic-fp32": False}  # fmt: skip
VARIANTS = (*TORCH_VARIANTS, "onnx-fp32", *OPENVINO_VARIANTS)
PEAK_SHAPE = (1024, 1024, 4096)  # m, k, n of the GEMM probes
Step = Callable[[], np.ndarray]  # one tracking step -> T_world_cam [4, 4]


# ---------------------------------------------------------------------------- FLOPs
@register_flop_formula(torch.ops.aten._scaled_dot_product_flash_attention_for_cpu)
def _cpu_flash_flops(
    query_shape: Sequence[int], key_shape: Sequence[int], value_shape: Sequence[int],
    *args: Any, **kwargs: Any,
) -> int:  # fmt: skip
    """Q·Kᵀ and A·V: 2·B·H·L·S·(E + Ev) (the counter knows only the CUDA attention kernels)."""
    batch, heads, queries, dim = query_shape
    keys, value_dim = key_shape[-2], value_shape[-1]
    return 2 * batch * heads * queries * keys * (dim + value_dim)


def count_flops(step: Callable[[], object]) -> int:
    with FlopCounterMode(display=False) as counter:
        step()
    return int(counter.get_total_flops())


# ---------------------------------------------------------------------------- the official step
def _official_forward_track(
    self: Attention, x: torch.Tensor, key_buffer: torch.Tensor, value_buffer: torch.Tensor,
    past_length: int, *, rope: Any = None, attn_mask: torch.Tensor | None = None,
) -> torch.Tensor:  # fmt: skip
    """The official per-layer cache read: concatenate the cached K/V with the frame's, then SDPA."""
    q, k, v = self.project(x, rope)
    keys = torch.cat((key_buffer[:, :, :past_length], k), dim=2)
    values = torch.cat((value_buffer[:, :, :past_length], v), dim=2)
    return self._merge(F.scaled_dot_product_attention(q, keys, values, attn_mask=attn_mask))


def _official_add_uv_embedding(
    x: torch.Tensor, image_size: tuple[int, int], ratio: float = 0.1
) -> torch.Tensor:
    """The official DPT head's ``_add_pos_embed``: the UV embedding computed on every call."""
    return x + dpt_blocks._scaled_uv_embedding(x, image_size, ratio)


@contextlib.contextmanager
def official_code(dtype: torch.dtype) -> Iterator[None]:
    """The official step's attention, and autocast to ``dtype`` over fp32 weights (bf16); DA3's
    DPT head as the official code runs it (NCHW convolutions, the UV embedding computed per
    call) instead of the SDK's (channels-last, the embedding reused)."""
    saved = (Attention.forward_track, dpt_blocks.PointwiseConv.forward,
             dualdpt._channels_last, dualdpt.add_uv_embedding)  # fmt: skip
    Attention.forward_track = _official_forward_track  # type: ignore[method-assign]
    dpt_blocks.PointwiseConv.forward = nn.Conv2d.forward  # type: ignore[method-assign]
    dualdpt._channels_last = lambda x: x
    dualdpt.add_uv_embedding = _official_add_uv_embedding
    try:
        with torch.autocast("cpu", dtype=dtype, enabled=dtype != torch.float32):
            yield
    finally:
        (Attention.forward_track, dpt_blocks.PointwiseConv.forward,  # type: ignore[method-assign]
         dualdpt._channels_last, dualdpt.add_uv_embedding) = saved  # fmt: skip


# ---------------------------------------------------------------------------- variants
class Variants:
    """Builds (once per model) what each variant needs and the step callables of a point."""

    def __init__(self, name: str, args: argparse.Namespace) -> None:
        self.name, self.args, self.notes = name, args, {}
        # one model per torch variant (a compiled one freezes its own weights); "fp32" serves
        # torch-fp32 and the official variants
        self.models = {"fp32": build_model(name, torch.float32)}
        self.compiled: dict[str, CompiledTracking] = {}
        for variant in args.variants:
            kind, _, dtype = variant.rpartition("-")
            if kind in ("official", "onnx") or variant in OPENVINO_VARIANTS or variant == "torch-fp32":
                continue
            model = build_model(name, DTYPES[dtype])
            if "products" in kind:
                use_cached_kernel(model, "products")
            if "compile" in kind:
                compiled = CompiledTracking(model, CompileOptions(freezing=not args.no_freezing))
                model.forward_track = compiled  # as TorchBackend(compile=...) does
                self.compiled[variant] = compiled
            self.models[variant] = model
        self.family = family_of(self.models["fp32"])
        self.exported: dict[str, Any] = {}
        wanted = set(args.variants)
        if wanted & {"onnx-fp32", *OPENVINO_VARIANTS}:
            self._export_backends(wanted)

    def _export_backends(self, wanted: set[str]) -> None:
        """ONNX Runtime / OpenVINO over one export of the fp32 model (made once, reused)."""
        from benchmarks.onnx_vs_torch import ensure_export
        from kvtracker_sdk.backends.onnx import OnnxBackend
        from kvtracker_sdk.backends.torch_backend import TorchBackend

        model = self.models["fp32"]
        if self.name == "pi3-large" and not self.args.export_large:
            self.notes["onnx/openvino"] = "Pi3 large not exported (~10 GB, ~9 min): --export-large"
            return
        # TorchBackend of the fp32 model (no copy; it stays fp32): its fingerprint names the export
        probe = TorchBackend(model, threads=self.args.threads)
        folder = ensure_export(probe, model, self.args.onnx_dir / self.name)
        if "onnx-fp32" in wanted:
            self.exported["onnx-fp32"] = OnnxBackend(folder, threads=self.args.threads)
        for variant in OPENVINO_VARIANTS:
            if variant not in wanted:
                continue
            precision = variant.rpartition("-")[2]
            try:
                from kvtracker_sdk.backends.openvino import (  # type: ignore[import-not-found]
                    OpenVinoBackend,
                )

                self.exported[variant] = OpenVinoBackend(
                    folder, precision=DTYPE_NAMES[precision], threads=self.args.threads,
                    static_shapes=OPENVINO_STATIC.get(variant),
                )  # fmt: skip
            except Exception as exc:  # not on this branch, or openvino missing
                self.notes[variant] = f"skipped: {type(exc).__name__}: {exc}"

    def steps(self, size: int, keyframes: int, heads: HeadSet, seed: int = 0) -> dict[str, Step]:
        """Each variant's step on the query frame of ``seed`` (0: the timed one)."""
        fp32 = self.models["fp32"]
        layout, tokens = self.family.cache_layout(fp32), fp32.tokens_per_frame(size, size)
        caches = {"fp32": random_cache(layout, torch.float32, keyframes, tokens)}
        caches["bf16"] = bf16_copy(caches["fp32"], keyframes, tokens, layout)
        image = np.random.default_rng(seed).integers(0, 256, (1, size, size, 3), dtype=np.uint8)
        frames = torch.from_numpy(image).permute(0, 3, 1, 2).float().div(255.0)
        family = self.family

        def torch_step(model: Any, cache: KVCache, context: Any = contextlib.nullcontext) -> Step:
            def step() -> np.ndarray:
                with torch.no_grad(), context():
                    return np.asarray(family.track(model, frames, cache, heads).poses[0])

            return step

        steps: dict[str, Step] = {}
        for variant in self.args.variants:
            kind, _, dtype = variant.rpartition("-")
            if variant == "torch-fp32":
                steps[variant] = torch_step(fp32, caches["fp32"])
            elif variant in self.models:
                steps[variant] = torch_step(self.models[variant], caches[dtype])
            elif kind == "official":
                context = lambda d=DTYPES[dtype]: official_code(d)  # noqa: E731
                steps[variant] = torch_step(fp32, caches[dtype], context)
            elif variant in self.exported:
                backend = self.exported[variant]
                steps[variant] = lambda b=backend, c=caches["fp32"]: np.asarray(
                    b.track(image[0], c, heads=heads).pose
                )
        return steps


DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16}
DTYPE_NAMES = {"fp32": "float32", "bf16": "bfloat16"}


def bf16_copy(cache: KVCache, keyframes: int, tokens: int, layout: Any) -> KVCache:
    """The fp32 random cache's values rounded to bf16 (the same map in the bf16 runtimes)."""
    keys = [cache.buffers(i)[0][:, :, : keyframes * tokens].to(torch.bfloat16)
            for i in range(layout.num_layers)]  # fmt: skip
    values = [cache.buffers(i)[1][:, :, : keyframes * tokens].to(torch.bfloat16)
              for i in range(layout.num_layers)]  # fmt: skip
    return KVCache.from_layers(keys, values, layout=layout, tokens_per_frame=tokens,
                               keyframe_ids=range(keyframes))  # fmt: skip


def gemm_probe(dtype: torch.dtype) -> Callable[[], torch.Tensor]:
    """One ``PEAK_SHAPE`` matrix product in ``dtype`` (oneDNN/MKL: the machine's matmul rate)."""
    m, k, n = PEAK_SHAPE
    a = torch.randn(m, k, generator=torch.Generator().manual_seed(1)).to(dtype)
    b = torch.randn(k, n, generator=torch.Generator().manual_seed(2)).to(dtype)
    return lambda: torch.mm(a, b)


# ---------------------------------------------------------------------------- timing
def time_point(steps: dict[str, Callable[[], Any]], args: argparse.Namespace) -> dict[str, Any]:
    """Interleaved rounds over ``steps`` (after their first calls): per step its samples (wall,
    cpu) and the cores other processes used per round."""
    names = list(steps)
    samples: dict[str, dict[str, list[float]]] = {n: {"wall": [], "cpu": []} for n in names}
    others: list[float] = []
    for round_index in range(args.warmup + args.rounds):
        shift = round_index % len(names)
        load = OtherLoad()
        for name in names[shift:] + names[:shift]:
            wall, cpu = time.perf_counter(), time.process_time()
            steps[name]()
            if round_index >= args.warmup:
                samples[name]["wall"].append(time.perf_counter() - wall)
                samples[name]["cpu"].append(time.process_time() - cpu)
        others.append(load.cores())
    return {"samples": samples, "others_cores": others}


def run_point(variants: Variants, size: int, keyframes: int, heads: str,
              args: argparse.Namespace) -> dict[str, Any]:  # fmt: skip
    steps = variants.steps(size, keyframes, HEADS[heads])
    poses, first_call = {}, {}
    for name, step in steps.items():  # first calls: compilation, export sessions' warm-up
        start = time.perf_counter()
        poses[name] = step()
        first_call[name] = time.perf_counter() - start
    flops = count_flops(steps["torch-fp32"]) if "torch-fp32" in steps else None
    more_frames = pose_deviations(variants, size, keyframes, heads, args.pose_frames)
    probes = {"peak-bf16": gemm_probe(torch.bfloat16), "peak-fp32": gemm_probe(torch.float32)}
    load_start = os.getloadavg()
    timed = time_point({**steps, **probes}, args)
    clock = args.clock
    best = {name: min(s[clock]) for name, s in timed["samples"].items()}
    m, k, n = PEAK_SHAPE
    peak = {d: 2 * m * k * n / best[f"peak-{d}"] for d in ("bf16", "fp32")}
    rows = {}
    reference = poses.get("torch-fp32")
    for name in steps:
        dtype = name.rpartition("-")[2]  # the GEMM peak of the variant's matmul dtype
        limit = None if flops is None else flops / peak[dtype]
        rows[name] = {
            "best_s": best[name],
            "median_s": statistics.median(timed["samples"][name][clock]),
            "first_call_s": first_call[name],
            "limit_s": limit,
            "fraction_of_limit": None if limit is None else limit / best[name],
            # against the fastest GEMM measured (bf16): comparable across dtypes and runtimes
            "fraction_of_peak_limit": None if flops is None
            else flops / max(peak.values()) / best[name],
            "pose_deviation": None if reference is None
            else float(np.abs(poses[name] - reference).max()),
            **more_frames.get(name, {}),
        }  # fmt: skip
    official = best.get("official-bf16")
    for row in rows.values():
        row["speedup_vs_official_bf16"] = None if official is None else official / row["best_s"]
    return {
        "model": variants.name, "size": size, "keyframes": keyframes, "heads": heads,
        "flops": flops, "peak_flops_per_s": peak, "rows": rows, "clock": clock,
        "samples": timed["samples"], "others_cores": timed["others_cores"],
        "load_average_start": load_start, "load_average_end": os.getloadavg(),
    }  # fmt: skip


def pose_deviations(variants: Variants, size: int, keyframes: int, heads: str,
                    frames: int) -> dict[str, dict[str, float]]:  # fmt: skip
    """Per variant, the largest and the mean pose deviation from ``torch-fp32`` over ``frames``
    query frames (seeds 0..frames-1; one frame's deviation varies 2-3x between frames)."""
    deviations: dict[str, list[float]] = {}
    for seed in range(frames if frames > 1 else 0):
        steps = variants.steps(size, keyframes, HEADS[heads], seed=seed)
        if "torch-fp32" not in steps:
            return {}
        reference = steps["torch-fp32"]()
        for name, step in steps.items():
            deviations.setdefault(name, []).append(float(np.abs(step() - reference).max()))
    return {name: {"pose_deviation_max": max(d), "pose_deviation_mean": statistics.fmean(d),
                   "pose_frames": len(d)} for name, d in deviations.items()}  # fmt: skip


# ---------------------------------------------------------------------------- output
def markdown_table(points: list[dict[str, Any]]) -> str:
    lines = [
        "| model | size | N | heads | GFLOP | variant | best (s) | median (s) | limit (s) "
        "| of limit | vs official bf16 | pose dev. | load avg |",
        "|---|---:|---:|---|---:|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for point in points:
        load = f"{point['load_average_start'][0]:.1f}→{point['load_average_end'][0]:.1f}"
        gflop = "—" if point["flops"] is None else f"{point['flops'] / 1e9:.2f}"
        for name, row in point["rows"].items():
            def fmt(value: float | None, spec: str) -> str:
                return "—" if value is None else format(value, spec)

            lines.append(
                f"| {point['model']} | {point['size']} | {point['keyframes']} | {point['heads']} "
                f"| {gflop} | {name} | {row['best_s']:.4f} | {row['median_s']:.4f} "
                f"| {fmt(row['limit_s'], '.4f')} | {fmt(row['fraction_of_limit'], '.0%')} "
                f"| {fmt(row['speedup_vs_official_bf16'], '.2f')}× "
                f"| {fmt(row['pose_deviation'], '.1e')}{more_frames_text(row)} | {load} |"
            )
    peaks = [f"{p['model']} {p['size']} N={p['keyframes']}: bf16 "
             f"{p['peak_flops_per_s']['bf16'] / 1e9:.0f}, fp32 "
             f"{p['peak_flops_per_s']['fp32'] / 1e9:.0f} GFLOP/s" for p in points]  # fmt: skip
    return "\n".join(lines) + "\n\nGEMM peak in the same rounds: " + "; ".join(peaks)


def more_frames_text(row: dict[str, Any]) -> str:
    """" (K frames: max / mean)" when ``--pose-frames`` measured them."""
    if "pose_deviation_max" not in row:
        return ""
    return (f" ({row['pose_frames']} frames: {row['pose_deviation_max']:.1e} max / "
            f"{row['pose_deviation_mean']:.1e} mean)")  # fmt: skip


def summary_table(points: list[dict[str, Any]]) -> str:
    """One line per point: each variant's speed-up over the official bf16 step, and the best
    variant with its fraction of the FLOP limit and its pose deviation from fp32."""
    names = list(dict.fromkeys(name for point in points for name in point["rows"]))
    lines = ["| model | size | N | heads | GFLOP | " + " | ".join(names)
             + " | fastest: of the bf16-GEMM limit, pose dev. | load avg |",
             "|---|---:|---:|---|---:|" + "---:|" * len(names) + "---|---|"]  # fmt: skip
    for point in points:
        rows = point["rows"]
        cells = []
        for name in names:
            speedup = rows.get(name, {}).get("speedup_vs_official_bf16")
            cells.append("—" if speedup is None else f"{speedup:.2f}×")
        fastest = min(rows, key=lambda name: rows[name]["best_s"])
        best = rows[fastest]
        fraction, deviation = best.get("fraction_of_peak_limit"), best["pose_deviation"]
        fraction_text = "—" if fraction is None else f"{fraction:.0%}"
        deviation_text = "—" if deviation is None else f"{deviation:.1e}"
        gflop = "—" if point["flops"] is None else f"{point['flops'] / 1e9:.1f}"
        lines.append(
            f"| {point['model']} | {point['size']} | {point['keyframes']} | {point['heads']} "
            f"| {gflop} | " + " | ".join(cells)
            + f" | {fastest}: {fraction_text}, {deviation_text} "
            f"| {point['load_average_start'][0]:.1f}→{point['load_average_end'][0]:.1f} |"
        )
    return "\n".join(lines)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add = parser.add_argument
    add("--models", nargs="+", choices=list(MODELS), default=["da3-small", "da3-base", "pi3-large"])
    add("--sizes", nargs="+", type=int, default=[224, 308], help="square sides, multiples of 14")
    add("--keyframes", nargs="+", type=int, default=[1, 8, 32])
    add("--heads", nargs="+", choices=list(HEADS), default=["camera", "conf"])
    add("--variants", nargs="+", choices=VARIANTS,
        default=["torch-fp32", "torch-bf16", "compile-bf16", "official-bf16", "official-fp32",
                 "onnx-fp32", "openvino-bf16"])  # fmt: skip
    add("--rounds", type=int, default=5, help="timed rounds per point")
    add("--pose-frames", type=int, default=1,
        help="also the pose deviation's max and mean over this many query frames")
    add("--warmup", type=int, default=1, help="untimed rounds per point after the first calls")
    add("--threads", type=int, default=1)
    add("--clock", choices=["cpu", "wall"], default="cpu")
    add("--no-freezing", action="store_true", help="compile without Inductor's freezing")
    add("--export-large", action="store_true", help="also export Pi3 large for ORT/OpenVINO")
    add("--onnx-dir", type=Path, default=Path(tempfile.gettempdir()) / "kvtracker-runtimes-onnx")
    add("--summary", type=Path, help="only re-print a saved JSON's summary table")
    add("--name", default="runtimes")
    add("--out-dir", type=Path, default=RESULTS)
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    if args.summary:
        saved: dict[str, Any] = json.loads(args.summary.read_text())
        print(summary_table(saved["points"]))
        return saved
    torch.set_num_threads(args.threads)
    result: dict[str, Any] = {
        "argv": list(argv) if argv is not None else None, "threads": args.threads,
        "clock": args.clock, "rounds": args.rounds, "peak_shape": PEAK_SHAPE,
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                    "torch": torch.__version__,
                    "cpu_capability": torch.backends.cpu.get_cpu_capability()},
        "load_average_start": os.getloadavg(), "points": [], "notes": {},
    }  # fmt: skip
    args.out_dir.mkdir(parents=True, exist_ok=True)
    path = args.out_dir / f"{args.name}.json"
    for name in args.models:
        variants = Variants(name, args)
        result["notes"][name] = variants.notes
        for size in args.sizes:
            for keyframes in args.keyframes:
                for heads in args.heads:
                    point = run_point(variants, size, keyframes, heads, args)
                    result["points"].append(point)
                    print(markdown_table([point]), flush=True)
                    result["load_average_end"] = os.getloadavg()
                    path.write_text(json.dumps(result, indent=1) + "\n")  # kept if stopped
        result.setdefault("compile", {}).update({
            f"{name} {variant}": {"status": c.report.status, "first_call_s": c.report.first_call_s,
                                "cache_dir": str(c.report.cache_dir)}
            for variant, c in variants.compiled.items()
        })  # fmt: skip
        result.setdefault("openvino_static_compiles", {}).update({
            f"{name} {variant}": backend.static_compiles for variant, backend
            in variants.exported.items() if hasattr(backend, "static_compiles")
        })  # fmt: skip
        del variants
    path.write_text(json.dumps(result, indent=1) + "\n")
    print("\n" + markdown_table(result["points"]) + "\n\n" + summary_table(result["points"]))
    print(f"notes: {result['notes']}\nwrote {path}")
    return result


if __name__ == "__main__":
    main()

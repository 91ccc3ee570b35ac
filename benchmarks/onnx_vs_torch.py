"""ONNX Runtime vs PyTorch eager: the cached tracking step on CPU, per number of keyframes N.

For each config — Pi3 (``tracking_vs_recompute.PRESETS``: ``mid``, ``large``, ``tiny``) or
Depth Anything 3 (``model_families.MODELS``: ``da3-small``, ``da3-base``, ``da3-tiny``) — the
same random-weight network runs as ``TorchBackend`` (fp32) and, exported once (reused from
``--onnx-dir/<config>`` when its fingerprint matches), as ``OnnxBackend`` (fp32). With
``--int8`` the tracking graphs are also quantised with ONNX Runtime's dynamic int8 quantisation
(int8 weights per channel, activations quantised at run time; VNNI/AMX kernels on x86) and
timed through the same runner. One query frame is tracked against a cache of N random keyframes
(``model_families.random_cache``: the values do not change the work).

Timing: the variants are timed in turn within each repeat (so a busy shared machine slows them
alike); the table shows the best of ``--repeats`` on ``--clock``. PyTorch flushes denormals to
zero (``--keep-denormals`` turns it off): with 2 threads, the random-weight models' denormal
activations slowed some of its kernels 10x (mid: 5.6 s instead of 0.4 s a step), a pathology
of the benchmark's weights, not of eager PyTorch; ONNX Runtime did not show it. The pose difference of each
variant against PyTorch on the same cache is recorded (random weights: int8 accuracy on real
weights needs the real checkpoint).

    python -m benchmarks.onnx_vs_torch --config mid large --keyframes 1 8 32 --threads 2 --int8
    python -m benchmarks.onnx_vs_torch --config da3-small da3-base --keyframes 1 8 32 --int8
    python -m benchmarks.onnx_vs_torch --config tiny --weights model.safetensors   # a checkpoint

Writes ``benchmarks/results/<name>.json`` (default ``onnx_vs_torch_<size>_<threads>thread``).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks import model_families
from benchmarks.tracking_vs_recompute import HEADS, PRESETS, build_model
from kvtracker_sdk.backends.onnx import OnnxBackend
from kvtracker_sdk.backends.onnx_manifest import FAMILY_GRAPHS, read_manifest
from kvtracker_sdk.backends.onnx_runtime import OnnxRunner
from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.errors import ModelError
from kvtracker_sdk.export_onnx import export_model
from kvtracker_sdk.models.registry import family_of, load_model

RESULTS = Path(__file__).parent / "results"
DA3_CONFIGS = sorted(name for name in model_families.MODELS if name.startswith("da3-"))


def tracking_graphs(family: str) -> tuple[str, ...]:
    """The graphs a tracking step runs (the quantised ones): no mapping decoder, no points."""
    return tuple(g for g in FAMILY_GRAPHS[family] if g not in ("decoder_map", "head_points"))


def ensure_export(backend: TorchBackend, model: torch.nn.Module, folder: Path) -> Path:
    """``folder`` holding an export of ``model``: reused when its fingerprint matches."""
    try:
        if read_manifest(folder).fingerprint == backend.info.fingerprint:
            return folder
    except ModelError:
        pass
    print(f"exporting to {folder} ...", flush=True)
    export_model(model, folder, overwrite=True)  # type: ignore[arg-type]
    return folder


def quantize_graphs(folder: Path, target: Path) -> None:
    """int8 dynamic quantisation of the tracking graphs from ``folder`` into ``target``."""
    import onnx
    from onnxruntime.quantization import QuantType, quantize_dynamic

    target.mkdir(exist_ok=True)
    for graph in tracking_graphs(read_manifest(folder).family):
        if (target / f"{graph}.onnx").is_file():
            continue
        print(f"quantising {graph} to int8 ...", flush=True)
        model = onnx.load(folder / f"{graph}.onnx")
        del model.graph.value_info[:]  # the tool's Gemm->MatMul rewrite conflicts with them
        partial = target / f"{graph}.partial.onnx"  # renamed once complete: never half-read
        quantize_dynamic(
            model, partial, weight_type=QuantType.QInt8, per_channel=True,
            use_external_data_format=True,
        )  # fmt: skip
        os.replace(partial, target / f"{graph}.onnx")  # its data file keeps the partial name


def ensure_int8(folder: Path, threads: int) -> OnnxRunner:
    """A runner over int8 quantisations of the tracking graphs, made once in ``<folder>-int8``.

    The quantiser holds a graph's fp32 weights several times over: it runs in a child process,
    so that its memory (7 GB for the full decoder) is returned before the timing starts. When
    every graph is already quantised no child is started (spawning one costs ~2 s of CPU).
    """
    target = folder.with_name(folder.name + "-int8")
    manifest = read_manifest(folder)
    graphs = tracking_graphs(manifest.family)
    if not all((target / f"{graph}.onnx").is_file() for graph in graphs):
        worker = multiprocessing.get_context("spawn").Process(
            target=quantize_graphs, args=(folder, target)
        )
        worker.start()
        worker.join()
        if worker.exitcode != 0:
            raise RuntimeError(f"int8 quantisation failed (exit code {worker.exitcode})")
    subset = {name: manifest.graphs[name] for name in graphs}
    return OnnxRunner(target, manifest.model_copy(update={"graphs": subset}), threads=threads)


def time_variants(
    steps: dict[str, Callable[[], np.ndarray]], warmup: int, repeats: int
) -> dict[str, dict[str, list[float]]]:
    """Wall and process-CPU seconds of every step, the steps taking turns in each repeat."""
    for step in steps.values():
        for _ in range(warmup):
            step()
    samples: dict[str, dict[str, list[float]]] = {name: {"wall": [], "cpu": []} for name in steps}
    for _ in range(repeats):
        for name, step in steps.items():
            start_wall, start_cpu = time.perf_counter(), time.process_time()
            step()
            samples[name]["wall"].append(time.perf_counter() - start_wall)
            samples[name]["cpu"].append(time.process_time() - start_cpu)
    return samples


def bench_config(
    name: str, args: argparse.Namespace, configs: dict[str, Any]
) -> list[dict[str, Any]]:
    """Rows (one per N and head set) for preset ``name``; its architecture goes to ``configs``."""
    if args.weights is not None:  # a checkpoint instead of a random-weight preset
        model: torch.nn.Module = load_model(args.weights).model
    elif name in PRESETS:
        model = build_model(PRESETS[name](), torch.float32)
    else:
        model = model_families.build_model(name, torch.float32)
    configs[name] = model.config.model_dump(mode="json")  # type: ignore[operator]
    torch_backend = TorchBackend(model, model_name=name)  # type: ignore[arg-type]
    layout = family_of(model).cache_layout(model)  # type: ignore[arg-type]
    folder = ensure_export(torch_backend, model, args.onnx_dir / name)
    int8 = ensure_int8(folder, args.threads) if args.int8 else None
    onnx_backend = OnnxBackend(folder, threads=args.threads)
    size = args.size
    image = np.random.default_rng(0).integers(0, 256, (size, size, 3), dtype=np.uint8)
    frame = np.ascontiguousarray(image.transpose(2, 0, 1)[None], dtype=np.float32) / 255.0
    rows = []
    for keyframes in args.keyframes:
        tokens = model.tokens_per_frame(size, size)  # type: ignore[operator]
        cache = model_families.random_cache(layout, torch.float32, keyframes, tokens)
        past = [tuple(b.numpy() for b in cache.buffers(i)) for i in range(cache.layout.num_layers)]
        for heads_name in args.heads:
            heads = HEADS[heads_name]
            steps: dict[str, Callable[[], np.ndarray]] = {
                "torch_fp32": lambda h=heads, c=cache: torch_backend.track(image, c, heads=h).pose,
                "onnx_fp32": lambda h=heads, c=cache: onnx_backend.track(image, c, heads=h).pose,
            }
            if int8 is not None:
                steps["onnx_int8"] = lambda h=heads, p=past, n=cache.length: int8.track(
                    frame, p, n, h  # type: ignore[arg-type]
                ).poses[0]
            reference = steps["torch_fp32"]()
            pose_error = {k: float(np.abs(step() - reference).max()) for k, step in steps.items()}
            rows.append({
                "config": name, "keyframes": keyframes, "heads": heads_name,
                "cache_bytes": cache.nbytes, "pose_max_abs_diff_vs_torch": pose_error,
                **time_variants(steps, args.warmup, args.repeats),
                "load_average": os.getloadavg(),
            })  # fmt: skip
            print(f"{name} N={keyframes} {heads_name}: " + ", ".join(
                f"{k} {min(rows[-1][k][args.clock]):.3f} s" for k in steps), flush=True)  # fmt: skip
        del cache, past
    onnx_backend.close()
    return rows


def markdown_table(result: dict[str, Any]) -> str:
    """config | N | heads | PyTorch fp32 | ORT fp32 | speedup | (ORT int8 | speedup | pose diff)."""
    clock = result["clock"]
    int8 = any("onnx_int8" in row for row in result["rows"])
    header = "| config | N | heads | PyTorch fp32 (s) | ORT fp32 (s) | ORT fp32 speedup |"
    rule = "|---|---:|---|---:|---:|---:|"
    if int8:
        header += " ORT int8 (s) | ORT int8 speedup | int8 max pose diff |"
        rule += "---:|---:|---:|"
    lines = [header, rule]
    for row in result["rows"]:
        base, fp32 = min(row["torch_fp32"][clock]), min(row["onnx_fp32"][clock])
        line = (f"| {row['config']} | {row['keyframes']} | {row['heads']} | {base:.3f} | {fp32:.3f} "
                f"| {base / fp32:.2f}x |")  # fmt: skip
        if int8:
            q = min(row["onnx_int8"][clock])
            error = row["pose_max_abs_diff_vs_torch"]["onnx_int8"]
            line += f" {q:.3f} | {base / q:.2f}x | {error:.1e} |"
        lines.append(line)
    return "\n".join(lines)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--config", choices=sorted(PRESETS) + DA3_CONFIGS, nargs="+", default=["mid", "large"]
    )
    parser.add_argument("--size", type=int, default=224, help="square side in px, multiple of 14")
    parser.add_argument("--keyframes", type=int, nargs="+", default=[1, 8, 32])
    parser.add_argument("--heads", choices=sorted(HEADS), nargs="+", default=["camera", "conf"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--int8", action="store_true", help="also time int8 dynamic quantisation")
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--clock", choices=["wall", "cpu"], default="wall")
    parser.add_argument("--keep-denormals", action="store_true", help="PyTorch: no flush to zero")
    parser.add_argument("--onnx-dir", type=Path,
                        default=Path(tempfile.gettempdir()) / "kvtracker-onnx-bench")  # fmt: skip
    parser.add_argument("--weights", type=Path,
                        help="time this checkpoint (fp32) instead of --config's random weights; "
                             "--config then only names it")  # fmt: skip
    parser.add_argument("--name", help="output file stem")
    parser.add_argument("--out-dir", type=Path, default=RESULTS)
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the benchmark; print the table, write JSON; return the JSON content."""
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.set_flush_denormal(not args.keep_denormals)
    import onnxruntime

    result: dict[str, Any] = {
        "configs": {},  # name -> the architecture, filled as each network is built
        "resolution": [args.size, args.size], "threads": args.threads, "clock": args.clock,
        "warmup": args.warmup, "repeats": args.repeats, "load_average_start": os.getloadavg(),
        "torch_flush_denormal": not args.keep_denormals,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                    "torch": torch.__version__, "onnxruntime": onnxruntime.__version__,
                    "cpu_capability": torch.backends.cpu.get_cpu_capability()},
        "rows": [],
    }  # fmt: skip
    for name in args.config:
        result["rows"] += bench_config(name, args, result["configs"])
    result["load_average_end"] = os.getloadavg()
    args.out_dir.mkdir(parents=True, exist_ok=True)
    path = args.out_dir / f"{args.name or f'onnx_vs_torch_{args.size}_{args.threads}thread'}.json"
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(markdown_table(result))
    print(f"wrote {path}")
    return result


if __name__ == "__main__":
    main()

"""The SDK on a CUDA GPU in one short run: parity, bf16 accuracy, the tracking step, a session.

Sections (``--sections``; each is written to the JSON and the Markdown as soon as it ends, so a
run stopped by its time limit still leaves what it measured):

- ``device``: GPU, driver, CUDA and torch versions, TF32 flags.
- ``peak``: a bf16 matrix product (8192³, median of 10 after 3 warm-ups, CUDA events): the FLOP
  rate the tracking steps' FLOP limit is computed with, measured in the same run.
- ``upload``: one 308x308 uint8 frame to the GPU from pageable vs page-locked memory.
- ``parity``: the golden Pi3 (both cases) and DA3 models in fp32 on the GPU against the golden
  vectors, with the CPU tests' tolerances (Pi3 poses 1e-5, conf 1e-4, points 1e-4 + 1e-4 rel;
  DA3 pose 1e-5, intrinsics 1e-5 rel, maps 1e-4 + 1e-5 rel; K/V 1e-5): full forward, mapping
  pass with its K/V, the cached queries (the tracked poses), eager and replayed from a CUDA graph.
  Run with PyTorch's default flags (cuDNN may use TF32 for convolutions) and again with TF32 off.
- ``bf16``: on the golden models, bf16 against fp32 two ways, as the CPU precision tests do: the
  official recipe (``torch.autocast('cuda', bfloat16)`` over the fp32 model) and the SDK's
  ``set_precision(bfloat16)``; median and worst deviation per quantity (mapping and tracking
  poses, points / depth). The SDK must be no worse (up to the tests' 1e-3 relative slack).
- ``steps``: the tracking step of one query frame against N random keyframes (random weights:
  the work does not depend on them) for Pi3 ``large``, DA3-Small and DA3-Base at ``--size``,
  camera head only and with confidence, per variant: ``eager-bf16`` (the SDK's step),
  ``graph-bf16`` (CUDA graph, capacity ladder up to ``--budget`` keyframes), ``graph-flat-bf16``
  (one graph of ``--budget`` keyframes for every N) and ``official-bf16`` (the official code's
  step: fp32 weights under CUDA autocast, each global layer ``torch.cat``-ing the cache with the
  frame's K/V before SDPA). Variants take turns in every round; per step the wall time from the
  call to the pose on the host (the step ends in a host copy). FLOPs are counted on the eager
  step (``torch.utils.flop_counter``); limit = FLOPs / the bf16 peak.
- ``session``: a whole tracking session (``Tracker``, asynchronous mapping) on the simulated
  trajectory's real frames (the TUM fr2_desk images in ``--shared``) with Pi3 ``large`` (random
  weights) on the GPU: frames per second, the median step, and the worst frame while a rebuild
  runs in units of that step; with the CUDA graph and eager.
- ``compile``: ``torch.compile`` (Inductor, freezing) of the step at N = ``--budget``, camera
  head, Pi3 ``large`` then DA3-Small, timed beside eager and graph (last: compiling takes
  minutes; skipped when ``--budget-s`` is spent).

``--dry-run`` runs every section on the CPU with tiny models, a 28-pixel frame and N = 1, 2
(imports, shapes, the whole code path; graphs fall back to eager off CUDA).

    python -m benchmarks.gpu_check --dry-run
    python -m benchmarks.gpu_check --out "$OUT" --shared shared --budget-s 330   # on the GPU

Writes ``<out>/<name>.json`` and ``<out>/<name>.md``.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import os
import platform
import statistics
import subprocess
import sys
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch

from benchmarks.model_families import MODELS
from benchmarks.runtimes import _official_forward_track
from kvtracker_sdk.backends.cuda_graph_step import GraphOptions, GraphTracking
from kvtracker_sdk.backends.torch_compile import CompiledTracking, CompileOptions
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.models.layers.attention import Attention
from kvtracker_sdk.models.registry import family_of
from kvtracker_sdk.types import HeadSet

RESULTS = Path(__file__).parent / "results"
SHARED = Path(__file__).resolve().parents[2] / "shared"
HEADS = {"camera": HeadSet.CAMERA, "conf": HeadSet.CONFIDENCE}
SECTIONS = ("device", "peak", "upload", "parity", "bf16", "steps", "session", "compile")
ROUNDING = 1e-3  # the precision tests' relative slack (tests/models/bf16_deviation.py)


# ---------------------------------------------------------------------------- plumbing
class Run:
    """The results so far, written after every section."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args, self.start = args, time.perf_counter()
        self.device = torch.device("cpu" if args.dry_run else "cuda")
        self.result: dict[str, Any] = {
            "command": " ".join(sys.argv), "dry_run": args.dry_run,
            "date_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()),
            "sections": {}, "errors": {},
        }  # fmt: skip
        args.out.mkdir(parents=True, exist_ok=True)

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def out_of_time(self) -> bool:
        return self.elapsed() > self.args.budget_s

    def section(self, name: str, body: Callable[[Run], Any]) -> None:
        started = time.perf_counter()
        print(f"[{self.elapsed():6.1f}s] {name} ...", flush=True)
        try:
            self.result["sections"][name] = body(self)
        except Exception as exc:  # a section's failure is a result: the others still run
            self.result["errors"][name] = f"{type(exc).__name__}: {exc}"
            traceback.print_exc()
        finally:
            self.result.setdefault("section_seconds", {})[name] = time.perf_counter() - started
            self.write()

    def write(self) -> None:
        name = self.args.name
        (self.args.out / f"{name}.json").write_text(json.dumps(self.result, indent=1) + "\n")
        (self.args.out / f"{name}.md").write_text(markdown(self.result))


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn: Callable[[], Any], device: torch.device) -> float:
    sync(device)
    start = time.perf_counter()
    fn()
    sync(device)
    return time.perf_counter() - start


# ---------------------------------------------------------------------------- device, peak
def device_section(run: Run) -> dict[str, Any]:
    info: dict[str, Any] = {
        "torch": torch.__version__, "python": platform.python_version(),
        "platform": platform.platform(), "cpus": os.cpu_count(),
        "cuda_available": torch.cuda.is_available(),
    }  # fmt: skip
    if run.device.type == "cuda":
        props = torch.cuda.get_device_properties(run.device)
        info.update({
            "gpu": props.name, "memory_gib": props.total_memory / 2**30,
            "multiprocessors": props.multi_processor_count,
            "capability": f"{props.major}.{props.minor}", "cuda": torch.version.cuda,
            "cudnn": torch.backends.cudnn.version(),
            "matmul_allow_tf32": torch.backends.cuda.matmul.allow_tf32,
            "cudnn_allow_tf32": torch.backends.cudnn.allow_tf32,
        })  # fmt: skip
        with contextlib.suppress(Exception):
            query = ["nvidia-smi", "--query-gpu=name,driver_version,clocks.sm,clocks.max.sm,"
                     "temperature.gpu,power.draw", "--format=csv,noheader"]  # fmt: skip
            info["nvidia_smi"] = subprocess.run(
                query, capture_output=True, text=True, timeout=20
            ).stdout.strip()
    return info


def peak_section(run: Run) -> dict[str, Any]:
    """bf16 matrix product rate (random operands; zeros would run faster than real data)."""
    n = 256 if run.args.dry_run else 8192
    generator = torch.Generator(device=run.device).manual_seed(0)
    a = torch.randn(n, n, device=run.device, generator=generator).to(torch.bfloat16)
    b = torch.randn(n, n, device=run.device, generator=generator).to(torch.bfloat16)
    times = []
    for index in range(13):
        seconds = timed(lambda: torch.mm(a, b), run.device)
        if index >= 3:
            times.append(seconds)
    median = statistics.median(times)
    return {"n": n, "median_s": median, "bf16_flops_per_s": 2 * n**3 / median, "samples": times}


def upload_section(run: Run) -> dict[str, Any]:
    """One frame uint8 [308, 308, 3] -> the device, pageable vs page-locked (median of 200)."""
    size = 28 if run.args.dry_run else run.args.size
    frame = np.random.default_rng(0).integers(0, 256, (1, size, size, 3), dtype=np.uint8)
    rows: dict[str, Any] = {}
    for name in ("pageable", "pinned"):
        samples = []
        pinned = name == "pinned" and run.device.type == "cuda"

        def upload(pinned: bool = pinned) -> torch.Tensor:
            host = torch.from_numpy(frame)
            if pinned:
                return host.pin_memory().to(run.device, non_blocking=True)
            return host.to(run.device)

        for _ in range(200):
            samples.append(timed(upload, run.device))
        rows[name] = {"median_us": statistics.median(samples) * 1e6, "p99_us":
                      float(np.percentile(samples, 99)) * 1e6}  # fmt: skip
    return {"frame": [size, size, 3], **rows}


# ---------------------------------------------------------------------------- golden parity
def _load(path: Path) -> dict[str, torch.Tensor]:
    from safetensors.torch import load_file

    return load_file(str(path))


class Checks:
    """Named comparisons against golden tensors: worst |out - ref| and whether it is within
    atol + rtol * |ref| everywhere."""

    def __init__(self) -> None:
        self.rows: dict[str, dict[str, Any]] = {}

    def add(self, name: str, out: torch.Tensor, ref: torch.Tensor, atol: float, rtol: float) -> None:
        out, ref = out.detach().double().cpu(), ref.double().cpu()
        error = (out - ref).abs()
        allowed = atol + rtol * ref.abs()
        self.rows[name] = {
            "max_abs": float(error.max()), "atol": atol, "rtol": rtol,
            "worst_fraction_of_tolerance": float((error / allowed).max()),
            "ok": bool((error <= allowed).all()) and out.shape == ref.shape,
        }  # fmt: skip

    def summary(self) -> dict[str, Any]:
        return {"ok": all(r["ok"] for r in self.rows.values()), "checks": self.rows}


def _graphed(model: torch.nn.Module) -> SimpleNamespace:
    """``model`` whose ``forward_track`` is replayed from CUDA graphs (eager off CUDA)."""
    runner = GraphTracking(model, family_of(model).cache_layout(model), GraphOptions(8, ladder=True))
    return SimpleNamespace(forward_track=runner, runner=runner)


def pi3_parity(run: Run, checks: Checks) -> None:
    from kvtracker_sdk.models.pi3 import load_pi3
    from tests.models.pi3.test_golden_parity import CASES, cache_from_map, query_image

    folder = run.args.shared / "golden" / "pi3"
    model = load_pi3(folder / "weights.safetensors").model.to(run.device).eval()
    graphed = _graphed(model)

    def outputs(prefix: str, output: Any, expected: dict[str, torch.Tensor], key: str = "") -> None:
        checks.add(f"{prefix}.camera_poses", output.camera_poses, expected[key + "camera_poses"],
                   1e-5, 0)  # fmt: skip
        if output.conf is not None:
            checks.add(f"{prefix}.conf", output.conf, expected[key + "conf"], 1e-4, 0)
        for name in ("local_points", "points"):
            if getattr(output, name) is not None:
                checks.add(f"{prefix}.{name}", getattr(output, name), expected[key + name],
                           1e-4, 1e-4)  # fmt: skip

    with torch.no_grad():
        for case, (keyframes, queries) in sorted(CASES.items()):
            imgs = _load(folder / case / "inputs.safetensors")["imgs"].to(run.device)
            outputs(f"pi3.{case}.forward", model(imgs), _load(folder / case / "outputs.safetensors"))
            expected = _load(folder / case / "outputs_query.safetensors")
            mapped = model.forward_map(imgs[:, :keyframes])
            outputs(f"pi3.{case}.map", mapped.output, expected, "keyframes.")
            kv = _load(folder / case / "kv_cache.safetensors")
            for ordinal, block in enumerate(model.decoder.global_block_indices):
                checks.add(f"pi3.{case}.map.k{block}", mapped.keys[ordinal], kv[f"layer{block}.k"],
                           1e-5, 0)  # fmt: skip
                checks.add(f"pi3.{case}.map.v{block}", mapped.values[ordinal],
                           kv[f"layer{block}.v"], 1e-5, 0)  # fmt: skip
            cache = cache_from_map(model, imgs[:, :keyframes])
            for name in queries:
                query = query_image(imgs, keyframes, name)
                for label, network in (("track", model), ("graph", graphed)):
                    for heads in (HeadSet.ALL, HeadSet.CAMERA):
                        output = network.forward_track(query, cache, heads=heads)
                        outputs(f"pi3.{case}.{label}.{heads.name.lower()}.{name}", output, expected,
                                f"{name}.")  # fmt: skip
    checks.rows["pi3.graph_report"] = {"ok": True, **_report(graphed.runner)}


def _report(runner: GraphTracking) -> dict[str, Any]:
    report = runner.report
    return {"replays": report.replays, "eager": report.eager, "captures": dict(report.captures),
            "errors": list(report.errors)}  # fmt: skip


def da3_parity(run: Run, checks: Checks) -> None:
    from kvtracker_sdk.models.da3 import load_da3
    from tests.models.da3.test_golden_parity import CAMERA, GLOBAL_BLOCKS, MAPS, cache_from_map

    folder = run.args.shared / "golden" / "da3"
    model = load_da3(folder / "weights.safetensors").model.to(run.device).eval()
    graphed = _graphed(model)

    def outputs(prefix: str, output: Any, expected: dict[str, torch.Tensor], key: str = "") -> None:
        for name in CAMERA:
            checks.add(f"{prefix}.{name}", getattr(output, name), expected[key + name], 1e-5, 0)
        checks.add(f"{prefix}.intrinsics", output.intrinsics, expected[key + "intrinsics"], 0, 1e-5)
        for name in MAPS:
            if getattr(output, name) is not None:
                checks.add(f"{prefix}.{name}", getattr(output, name), expected[key + name],
                           1e-4, 1e-5)  # fmt: skip

    with torch.no_grad():
        imgs = _load(folder / "inputs.safetensors")["imgs_01"].to(run.device)
        output = model(imgs, ref_view_strategy="saddle_balanced", with_rays=True)
        outputs("da3.forward", output, _load(folder / "outputs.safetensors"))
        expected = _load(folder / "outputs_query.safetensors")
        mapped = model.forward_map(imgs[:, :3], with_rays=True)
        outputs("da3.map", mapped.output, expected, "keyframes.")
        kv = _load(folder / "kv_cache.safetensors")
        for ordinal, block in enumerate(GLOBAL_BLOCKS):
            checks.add(f"da3.map.k{block}", mapped.keys[ordinal], kv[f"layer{block}.k"], 1e-5, 0)
            checks.add(f"da3.map.v{block}", mapped.values[ordinal], kv[f"layer{block}.v"], 1e-5, 0)
        cache = cache_from_map(model, imgs[:, :3])
        for label, network in (("track", model), ("graph", graphed)):
            for heads in (HeadSet.ALL, HeadSet.CAMERA):
                output = network.forward_track(imgs[0, 3:4], cache, heads=heads, with_rays=True)
                outputs(f"da3.{label}.{heads.name.lower()}", output, expected, "query.")
    checks.rows["da3.graph_report"] = {"ok": True, **_report(graphed.runner)}


def backend_parity(run: Run, checks: Checks) -> None:
    """Tracked poses through ``TorchBackend`` in fp32 (eager and CUDA graph) against the golden
    queries; the fp32 backend turns cuDNN's TF32 off, which ``cudnn_tf32_after`` records."""
    from kvtracker_sdk.backends.torch_backend import TorchBackend
    from kvtracker_sdk.models.da3 import load_da3
    from kvtracker_sdk.models.pi3 import load_pi3

    golden = run.args.shared / "golden"
    cases = []
    for case, query in (("case1", "query"), ("case2", "query5")):
        imgs = _load(golden / "pi3" / case / "inputs.safetensors")["imgs"][0]
        keyframes = 3 if case == "case1" else 5
        expected = _load(golden / "pi3" / case / "outputs_query.safetensors")
        pose = expected[f"{query}.camera_poses"][0, 0].double()
        cases.append((f"pi3.{case}", lambda: load_pi3(golden / "pi3" / "weights.safetensors").model,
                      imgs, keyframes, pose))  # fmt: skip
    imgs = _load(golden / "da3" / "inputs.safetensors")["imgs_01"][0]
    extrinsics = _load(golden / "da3" / "outputs_query.safetensors")["query.extrinsics"][0, 0]
    world_to_cam = torch.eye(4, dtype=torch.float64)
    world_to_cam[:3] = extrinsics.double()
    cases.append(("da3", lambda: load_da3(golden / "da3" / "weights.safetensors").model, imgs, 3,
                  torch.linalg.inv(world_to_cam)))  # fmt: skip
    for label, load, imgs, keyframes, pose in cases:
        frames = imgs.permute(0, 2, 3, 1).contiguous().numpy()  # float32 [N, H, W, 3] in [0, 1]
        for variant, graph in (("backend", False), ("backend-graph", GraphOptions(8))):
            backend = TorchBackend(load(), device=run.device, cuda_graph=graph)
            mapped = backend.map(frames[:keyframes])
            for _ in range(2):  # the graph's first call captures, the second replays
                result = backend.track(frames[keyframes], mapped.cache)
            checks.add(f"{label}.{variant}.pose", torch.from_numpy(np.array(result.pose)), pose,
                       1e-5, 0)  # fmt: skip
            if backend.graph_report is not None:
                checks.rows[f"{label}.{variant}.graph"] = {
                    "ok": backend.graph_report.replays > 0 or run.device.type != "cuda",
                    "replays": backend.graph_report.replays, "eager": backend.graph_report.eager,
                    "errors": backend.graph_report.errors,
                }  # fmt: skip
    checks.rows["cudnn_tf32_after"] = {"ok": True, "value": torch.backends.cudnn.allow_tf32}


@contextlib.contextmanager
def tf32(enabled: bool | None) -> Iterator[None]:
    """cuDNN/cuBLAS TF32 flags for a block (None: leave PyTorch's defaults)."""
    saved = (torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32)
    if enabled is not None:
        torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = enabled
    try:
        yield
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


def parity_section(run: Run) -> dict[str, Any]:
    result = {}
    flags = [("default_flags", None)] + ([("tf32_off", False)] if run.device.type == "cuda" else [])
    for label, flag in flags:
        checks = Checks()
        with tf32(flag):
            for family_parity in (pi3_parity, da3_parity):
                try:
                    family_parity(run, checks)
                except Exception as exc:
                    checks.rows[family_parity.__name__] = {"ok": False, "error": repr(exc)}
                    traceback.print_exc()
        result[label] = checks.summary()
    checks = Checks()  # last: an fp32 backend on CUDA turns cuDNN's TF32 off for the process
    with tf32(None):
        try:
            backend_parity(run, checks)
        except Exception as exc:
            checks.rows["backend_parity"] = {"ok": False, "error": repr(exc)}
            traceback.print_exc()
    result["torch_backend"] = checks.summary()
    return result


# ---------------------------------------------------------------------------- bf16 accuracy
def bf16_section(run: Run) -> dict[str, Any]:
    from kvtracker_sdk.models.da3 import load_da3
    from kvtracker_sdk.models.pi3 import load_pi3
    from tests.models.da3 import test_precision as da3_precision
    from tests.models.pi3 import test_precision as pi3_precision
    from tests.models.pi3.test_golden_parity import CASES

    shared = run.args.shared / "golden"
    cases: list[tuple[str, torch.nn.Module, Callable[..., Any], dict[str, Any], torch.Tensor, int]]
    pi3 = load_pi3(shared / "pi3" / "weights.safetensors").model.eval()
    da3 = load_da3(shared / "da3" / "weights.safetensors").model.eval()
    cases = [
        (f"pi3.{case}", pi3, pi3_precision._map_and_track, pi3_precision.MEASURES,
         _load(shared / "pi3" / case / "inputs.safetensors")["imgs"], CASES[case][0])
        for case in sorted(CASES)
    ]  # fmt: skip
    cases.append(("da3", da3, da3_precision._map_and_track, da3_precision.MEASURES,
                  _load(shared / "da3" / "inputs.safetensors")["imgs_01"], 3))  # fmt: skip
    result: dict[str, Any] = {}
    for label, fp32_model, map_and_track, measures, imgs, keyframes in cases:
        fp32_model = fp32_model.to(run.device)
        sdk_model = copy.deepcopy(fp32_model).set_precision(torch.bfloat16)  # type: ignore[operator]
        imgs = imgs.to(run.device)
        ways = {
            "fp32": (fp32_model, contextlib.nullcontext()),
            "autocast": (fp32_model, torch.autocast(run.device.type, dtype=torch.bfloat16)),
            "sdk": (sdk_model, contextlib.nullcontext()),
        }
        outputs = {}
        with torch.no_grad():
            for way, (network, context) in ways.items():
                with context:
                    outputs[way] = {k: v.cpu() for k, v in
                                    map_and_track(network, imgs, keyframes).items()}  # fmt: skip
        rows = {}
        for quantity, measure in measures.items():
            sdk = measure(outputs["sdk"][quantity], outputs["fp32"][quantity])
            official = measure(outputs["autocast"][quantity], outputs["fp32"][quantity])
            limit = 1.0 + ROUNDING
            rows[quantity] = {
                "sdk": [sdk.median, sdk.worst], "autocast": [official.median, official.worst],
                "ok": sdk.median <= official.median * limit and sdk.worst <= official.worst * limit,
            }  # fmt: skip
        result[label] = rows
    result["ok"] = all(row["ok"] for rows in result.values() if isinstance(rows, dict)
                       for row in rows.values())  # fmt: skip
    return result


# ---------------------------------------------------------------------------- steps
@contextlib.contextmanager
def official_step(device: torch.device) -> Iterator[None]:
    """The official step: ``torch.cat`` of the cache with the frame's K/V per global layer, SDPA,
    under bf16 autocast over fp32 weights."""
    sdk = Attention.forward_track
    Attention.forward_track = _official_forward_track  # type: ignore[method-assign]
    try:
        with torch.autocast(device.type, dtype=torch.bfloat16):
            yield
    finally:
        Attention.forward_track = sdk  # type: ignore[method-assign]


def build(name: str, dtype: torch.dtype, device: torch.device, seed: int = 0) -> torch.nn.Module:
    """``name``'s network with PyTorch's random init made on ``device``, trunk in ``dtype``."""
    torch.manual_seed(seed)
    with torch.device(device):
        model = MODELS[name][0]().eval()
    return model.set_precision(dtype).requires_grad_(False)  # type: ignore[operator,no-any-return]


def random_cache(model: Any, keyframes: int, size: int, device: torch.device) -> KVCache:
    """N keyframes of random K/V (one tensor per layer, bf16) in a ``KVCache`` on ``device``."""
    layout = family_of(model).cache_layout(model)
    tokens = model.tokens_per_frame(size, size)
    generator = torch.Generator(device=device).manual_seed(keyframes)
    shape = (1, layout.num_heads, keyframes * tokens, layout.head_dim)
    keys = [torch.randn(shape, device=device, generator=generator).to(torch.bfloat16)
            for _ in range(layout.num_layers)]  # fmt: skip
    values = [torch.randn(shape, device=device, generator=generator).to(torch.bfloat16)
              for _ in range(layout.num_layers)]  # fmt: skip
    cache = KVCache.from_layers(keys, values, layout=layout, tokens_per_frame=tokens,
                                keyframe_ids=range(keyframes))  # fmt: skip
    del keys, values
    return cache


def count_flops(step: Callable[[], Any]) -> int:
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter:
        step()
    return int(counter.get_total_flops())


def interleaved(steps: dict[str, Callable[[], Any]], rounds: int, warmup: int,
                device: torch.device) -> dict[str, list[float]]:  # fmt: skip
    """Every step once per round, the order rotating; wall seconds per call after ``warmup``."""
    names = list(steps)
    samples: dict[str, list[float]] = {name: [] for name in names}
    for index in range(warmup + rounds):
        shift = index % len(names)
        for name in names[shift:] + names[:shift]:
            seconds = timed(steps[name], device)
            if index >= warmup:
                samples[name].append(seconds)
    return samples


class StepModels:
    """One model family's networks for the step timings (built once per model name)."""

    def __init__(self, name: str, run: Run) -> None:
        device = run.device
        self.name, self.device = name, device
        self.fp32 = build(name, torch.float32, device)  # the official step's weights
        self.bf16 = copy.deepcopy(self.fp32).set_precision(torch.bfloat16)  # type: ignore[operator]
        self.family = family_of(self.fp32)
        layout = self.family.cache_layout(self.bf16)
        budget = run.args.budget
        self.ladder = GraphTracking(self.bf16, layout, GraphOptions(budget, ladder=True))
        self.flat = GraphTracking(self.bf16, layout, GraphOptions(budget, ladder=False))
        # one keyframe more than the budget: at N = budget the masked graph (the others are full)
        self.masked = GraphTracking(self.bf16, layout, GraphOptions(budget + 1, ladder=False))

    def steps(self, frames: torch.Tensor, cache: KVCache, heads: HeadSet
              ) -> dict[str, Callable[[], np.ndarray]]:  # fmt: skip
        family, device = self.family, self.device

        def step(network: Any, context: Callable[[], Any] = contextlib.nullcontext
                 ) -> Callable[[], np.ndarray]:  # fmt: skip
            def call() -> np.ndarray:
                with torch.no_grad(), context():
                    return np.asarray(family.track(network, frames, cache, heads).poses[0])

            return call

        return {
            "eager-bf16": step(self.bf16),
            "graph-bf16": step(SimpleNamespace(forward_track=self.ladder)),
            "graph-flat-bf16": step(SimpleNamespace(forward_track=self.flat)),
            "graph-masked-bf16": step(SimpleNamespace(forward_track=self.masked)),
            "official-bf16": step(self.fp32, lambda: official_step(device)),
        }


def steps_section(run: Run) -> dict[str, Any]:
    args, device = run.args, run.device
    peak = run.result["sections"].get("peak", {}).get("bf16_flops_per_s")
    points: list[dict[str, Any]] = []
    result: dict[str, Any] = {"size": args.size, "budget": args.budget, "points": points,
                              "peak_bf16_flops_per_s": peak, "graph_reports": {}}  # fmt: skip
    for name in args.models:
        if run.out_of_time():
            result.setdefault("skipped", []).append(f"{name}: time budget spent")
            continue
        models = StepModels(name, run)
        frames = torch.rand(1, 3, args.size, args.size, device=device,
                            generator=torch.Generator(device=device).manual_seed(0))  # fmt: skip
        for keyframes in args.keyframes:
            cache = random_cache(models.bf16, keyframes, args.size, device)
            for heads in args.heads:
                steps = models.steps(frames, cache, HEADS[heads])
                poses = {label: step() for label, step in steps.items()}  # first calls, captures
                flops = count_flops(steps["eager-bf16"])
                samples = interleaved(steps, args.rounds, args.warmup, device)
                rows = {}
                for label, times in samples.items():
                    median = statistics.median(times)
                    rows[label] = {
                        "median_s": median, "best_s": min(times), "fps": 1.0 / median,
                        "pose_deviation_vs_eager": float(np.abs(poses[label]
                                                                - poses["eager-bf16"]).max()),
                        "fraction_of_limit": None if peak is None else flops / peak / median,
                    }  # fmt: skip
                official = rows["official-bf16"]["median_s"]
                for row in rows.values():
                    row["speedup_vs_official"] = official / row["median_s"]
                point = {"model": name, "size": args.size, "keyframes": keyframes, "heads": heads,
                         "flops": flops, "limit_s": None if peak is None else flops / peak,
                         "rows": rows, "samples": samples}  # fmt: skip
                points.append(point)
                print(step_lines([point]), flush=True)
                run.write()
            del cache
        result["graph_reports"][name] = {"ladder": _report(models.ladder),
                                         "flat": _report(models.flat),
                                         "masked": _report(models.masked)}  # fmt: skip
        del models
        if device.type == "cuda":
            torch.cuda.empty_cache()
    return result


def step_lines(points: list[dict[str, Any]]) -> str:
    lines = []
    for p in points:
        cells = ", ".join(f"{label} {row['median_s'] * 1e3:.2f} ms ({row['fps']:.0f} FPS, "
                          f"{row['speedup_vs_official']:.2f}x)" for label, row in p["rows"].items())
        lines.append(f"{p['model']} {p['size']} N={p['keyframes']} {p['heads']}: {cells}")
    return "\n".join(lines)


# ---------------------------------------------------------------------------- session
def tum_frames(run: Run) -> list[np.ndarray]:
    import cv2

    files = sorted((run.args.shared / "data" / "tum_fr2_desk" / "rgb").glob("*.png"))
    if not files:
        raise FileNotFoundError(f"no TUM frames under {run.args.shared}/data/tum_fr2_desk/rgb")
    return [cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB) for f in files]


def session_once(run: Run, backend: Any, frames: list[np.ndarray], count: int) -> dict[str, Any]:
    from kvtracker_sdk.config import TrackerConfig
    from kvtracker_sdk.tracking.facade.tracker import Tracker

    config = TrackerConfig.from_dict({
        "resolution": run.args.session_resolution, "threading": {"async_mapping": True},
        "keyframing": {"interval_frames": run.args.session_interval,
                       "budget": {"max_keyframes": run.args.session_keyframes}},
    })  # fmt: skip
    records = []
    with Tracker(config, backend) as tracker:
        start = time.perf_counter()
        for index in range(count):
            rebuilding_before = tracker.map_status.rebuilding
            t0 = time.perf_counter()
            result = tracker.push_frame(frames[index % len(frames)], timestamp=index / 30.0)
            seconds = time.perf_counter() - t0
            rebuilding = rebuilding_before or bool(result.extras.get("rebuilding"))
            records.append((seconds, rebuilding, "track" in result.timings_ms, result.pose_valid))
            if index == 0:  # the first map: tracking starts once it exists (not timed)
                tracker.wait_for_map(timeout=120)
                start += time.perf_counter() - t0 - seconds
        total = time.perf_counter() - start
        tracker.wait_for_map(timeout=120)
        status = tracker.map_status
    seconds = np.array([r[0] for r in records])
    during = np.array([r[1] for r in records])
    tracked = np.array([r[2] for r in records])
    calm = seconds[tracked & ~during]
    step = float(np.median(calm)) if len(calm) else float("nan")
    busy = seconds[tracked & during]
    return {
        "frames": count, "seconds": total, "fps": count / total, "median_step_s": step,
        "p99_step_s": float(np.percentile(seconds[tracked], 99)) if tracked.any() else None,
        "frames_during_rebuild": int((tracked & during).sum()),
        "worst_during_rebuild_s": float(busy.max()) if len(busy) else None,
        "worst_during_rebuild_steps": float(busy.max() / step) if len(busy) else None,
        "median_during_rebuild_steps": float(np.median(busy) / step) if len(busy) else None,
        "worst_any_steps": float(seconds[tracked].max() / step) if tracked.any() else None,
        "rebuilds": status.generation, "keyframes": status.num_keyframes,
        "valid_pose_fraction": float(np.mean([r[3] for r in records])),
        "frame_seconds": [round(float(s), 5) for s in seconds],
        "rebuilding": [bool(d) for d in during],
    }  # fmt: skip


def session_section(run: Run) -> dict[str, Any]:
    from kvtracker_sdk.backends.torch_backend import TorchBackend

    args = run.args
    frames = tum_frames(run)
    # one graph of the session's keyframe budget: no capture while the map grows
    variants = {"graph": {"cuda_graph": GraphOptions(args.session_keyframes, ladder=False)},
                "eager": {"cuda_graph": False}}  # fmt: skip
    variants = {label: variants[label] for label in args.session_variants}
    result: dict[str, Any] = {"model": args.session_model, "resolution": args.session_resolution,
                              "interval_frames": args.session_interval,
                              "max_keyframes": args.session_keyframes, "variants": {}}  # fmt: skip
    for label, options in variants.items():
        if run.out_of_time():
            result["variants"][label] = {"skipped": "time budget spent"}
            continue
        model = build(args.session_model, torch.float32, run.device)
        backend = TorchBackend(model, dtype=torch.bfloat16, device=run.device, **options)
        session_once(run, backend, frames, args.session_warmup)  # captures, kernel set-up
        row = session_once(run, backend, frames, args.session_frames)
        row["graph_report"] = None if backend.graph_report is None else {
            "replays": backend.graph_report.replays, "eager": backend.graph_report.eager,
            "captures": backend.graph_report.captures, "errors": backend.graph_report.errors,
            "cache_loads": backend.graph_report.cache_loads,
        }  # fmt: skip
        row["accelerations"] = list(backend.info.accelerations)
        result["variants"][label] = row
        print(f"session {label}: {row['fps']:.1f} FPS, step {row['median_step_s'] * 1e3:.2f} ms, "
              f"worst during rebuild {row['worst_during_rebuild_steps']} steps", flush=True)
        backend.close()
        del backend, model
        if run.device.type == "cuda":
            torch.cuda.empty_cache()
        run.write()
    return result


# ---------------------------------------------------------------------------- compile
def compile_section(run: Run) -> dict[str, Any]:
    args, device = run.args, run.device
    result: dict[str, Any] = {"keyframes": args.budget, "heads": "camera", "points": []}
    options = (CompileOptions(backend="eager", freezing=False) if args.dry_run
               else CompileOptions(freezing=True, dynamic=False))  # fmt: skip
    result["options"] = options.describe()
    for name in args.compile_models:
        if run.out_of_time():
            result.setdefault("skipped", []).append(f"{name}: time budget spent")
            continue
        models = StepModels(name, run)
        compiled = CompiledTracking(models.bf16, options)
        frames = torch.rand(1, 3, args.size, args.size, device=device,
                            generator=torch.Generator(device=device).manual_seed(0))  # fmt: skip
        cache = random_cache(models.bf16, args.budget, args.size, device)
        sdk = models.steps(frames, cache, HeadSet.CAMERA)
        family = models.family

        def compiled_step(c: Any = compiled, f: Any = family, k: KVCache = cache,
                          x: torch.Tensor = frames) -> np.ndarray:  # fmt: skip
            with torch.no_grad():
                proxy = SimpleNamespace(forward_track=c)
                return np.asarray(f.track(proxy, x, k, HeadSet.CAMERA).poses[0])

        steps = {"compile-bf16": compiled_step, "eager-bf16": sdk["eager-bf16"],
                 "graph-bf16": sdk["graph-bf16"]}  # fmt: skip
        first = {}
        poses = {}
        with torch.no_grad():
            for label, step in steps.items():
                start = time.perf_counter()
                poses[label] = step()
                first[label] = time.perf_counter() - start
        samples = interleaved(steps, args.rounds, args.warmup, device)
        rows = {label: {"median_s": statistics.median(times), "fps": 1 / statistics.median(times),
                        "first_call_s": first[label],
                        "pose_deviation_vs_eager": float(np.abs(poses[label]
                                                                - poses["eager-bf16"]).max())}
                for label, times in samples.items()}  # fmt: skip
        result["points"].append({"model": name, "rows": rows, "samples": samples,
                                 "compile_status": compiled.report.status})  # fmt: skip
        print(f"compile {name}: " + ", ".join(f"{k} {v['median_s'] * 1e3:.2f} ms"
                                              for k, v in rows.items()), flush=True)  # fmt: skip
        del models, compiled, cache
        run.write()
    return result


# ---------------------------------------------------------------------------- markdown
def markdown(result: dict[str, Any]) -> str:
    sections = result["sections"]
    lines = [f"# GPU check ({'dry run, CPU' if result['dry_run'] else 'CUDA'}), "
             f"{result['date_utc']} UTC", "", f"`{result['command']}`", ""]  # fmt: skip
    device = sections.get("device", {})
    lines += [f"Device: {device.get('gpu', 'cpu')}, nvidia-smi: {device.get('nvidia_smi', '—')}, "
              f"torch {device.get('torch')}, CUDA {device.get('cuda', '—')}, cuDNN "
              f"{device.get('cudnn', '—')}", ""]  # fmt: skip
    if "peak" in sections:
        lines += [f"bf16 matrix product ({sections['peak']['n']}³): "
                  f"{sections['peak']['bf16_flops_per_s'] / 1e12:.1f} TFLOP/s", ""]  # fmt: skip
    if "upload" in sections:
        up = sections["upload"]
        lines += [f"Frame upload {up['frame']}: pageable {up['pageable']['median_us']:.0f} µs, "
                  f"pinned {up['pinned']['median_us']:.0f} µs (medians)", ""]  # fmt: skip
    if "parity" in sections:
        for label, summary in sections["parity"].items():
            bad = [f"{k} ({v.get('max_abs', v.get('error'))})" for k, v in
                   summary["checks"].items() if not v["ok"]]  # fmt: skip
            worst = max((v.get("worst_fraction_of_tolerance", 0) for v in
                         summary["checks"].values()), default=0)  # fmt: skip
            lines.append(f"Golden parity fp32 ({label}): {'PASS' if summary['ok'] else 'FAIL'}, "
                         f"{len(summary['checks'])} checks, worst at {worst:.2f} of its "
                         f"tolerance" + (f"; failing: {', '.join(bad)}" if bad else ""))  # fmt: skip
        lines.append("")
    if "bf16" in sections:
        lines += ["| bf16 vs fp32 | quantity | SDK median / worst | autocast median / worst | ok |",
                  "|---|---|---|---|---|"]  # fmt: skip
        for label, rows in sections["bf16"].items():
            if not isinstance(rows, dict):
                continue
            for quantity, row in rows.items():
                lines.append(f"| {label} | {quantity} | {row['sdk'][0]:.2e} / {row['sdk'][1]:.2e} "
                             f"| {row['autocast'][0]:.2e} / {row['autocast'][1]:.2e} "
                             f"| {row['ok']} |")  # fmt: skip
        lines.append("")
    if "steps" in sections:
        steps = sections["steps"]
        lines += [f"Tracking step, {steps['size']} px, graph budget {steps['budget']} keyframes "
                  "(median ms, FPS, speed-up over the official step, fraction of the bf16 FLOP "
                  "limit):", "",
                  "| model | N | heads | GFLOP | limit ms | eager-bf16 | graph-bf16 | "
                  "graph-flat-bf16 | graph-masked-bf16 | official-bf16 |",
                  "|---|---:|---|---:|---:|---|---|---|---|---|"]
        for p in steps["points"]:
            cells = []
            for label in ("eager-bf16", "graph-bf16", "graph-flat-bf16", "graph-masked-bf16",
                          "official-bf16"):
                row = p["rows"].get(label)
                if row is None:
                    cells.append("—")
                    continue
                fraction = row["fraction_of_limit"]
                cells.append(f"{row['median_s'] * 1e3:.2f} ms, {row['fps']:.0f} FPS, "
                             f"{row['speedup_vs_official']:.2f}×"
                             + ("" if fraction is None else f", {fraction:.0%}"))  # fmt: skip
            limit = "—" if p["limit_s"] is None else f"{p['limit_s'] * 1e3:.2f}"
            lines.append(f"| {p['model']} | {p['keyframes']} | {p['heads']} | "
                         f"{p['flops'] / 1e9:.0f} | {limit} | " + " | ".join(cells) + " |")
        lines.append("")
    if "session" in sections:
        session = sections["session"]
        lines += [f"Session: {session['model']} at resolution {session['resolution']}, async "
                  f"mapping, a keyframe every {session['interval_frames']} frames, at most "
                  f"{session['max_keyframes']}:", "",
                  "| variant | FPS | median step ms | worst frame during a rebuild (steps) | "
                  "median during rebuilds (steps) | frames during rebuilds | rebuilds |",
                  "|---|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
        for label, row in session["variants"].items():
            if "fps" not in row:
                lines.append(f"| {label} | {row} |||||")
                continue
            lines.append(f"| {label} | {row['fps']:.1f} | {row['median_step_s'] * 1e3:.2f} | "
                         f"{_num(row['worst_during_rebuild_steps'])} | "
                         f"{_num(row['median_during_rebuild_steps'])} | "
                         f"{row['frames_during_rebuild']} | {row['rebuilds']} |")  # fmt: skip
        lines.append("")
    if "compile" in sections:
        for point in sections["compile"]["points"]:
            lines.append(f"torch.compile ({sections['compile']['options']}) {point['model']} "
                         f"N={sections['compile']['keyframes']} camera: " + ", ".join(
                             f"{k} {v['median_s'] * 1e3:.2f} ms (first call {v['first_call_s']:.1f}"
                             f" s)" for k, v in point["rows"].items()))  # fmt: skip
        lines.append("")
    if result["errors"]:
        lines += ["Errors:", ""] + [f"- {k}: {v}" for k, v in result["errors"].items()] + [""]
    lines.append(f"Section seconds: {json.dumps(result.get('section_seconds', {}))}")
    return "\n".join(lines) + "\n"


def _num(value: float | None) -> str:
    return "—" if value is None else f"{value:.2f}"


# ---------------------------------------------------------------------------- main
def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add = parser.add_argument
    add("--dry-run", action="store_true", help="every section on the CPU with tiny models")
    add("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS))
    add("--models", nargs="+", default=["pi3-large", "da3-small", "da3-base"])
    add("--compile-models", nargs="+", default=["pi3-large", "da3-small"])
    add("--size", type=int, default=308)
    add("--keyframes", nargs="+", type=int, default=[1, 8, 32, 50])
    add("--heads", nargs="+", choices=list(HEADS), default=["camera", "conf"])
    add("--budget", type=int, default=50, help="the graphs' keyframe capacity")
    add("--rounds", type=int, default=15)
    add("--warmup", type=int, default=3)
    add("--session-model", default="pi3-large")
    add("--session-resolution", type=int, default=308)
    add("--session-frames", type=int, default=300)
    add("--session-warmup", type=int, default=24)
    add("--session-interval", type=int, default=10)
    add("--session-keyframes", type=int, default=16)
    add("--session-variants", nargs="+", choices=["graph", "eager"], default=["graph", "eager"])
    add("--budget-s", type=float, default=330.0, help="sections after this many seconds skip")
    add("--shared", type=Path, default=SHARED)
    add("--out", type=Path, default=RESULTS)
    add("--name", default=None)
    args = parser.parse_args(argv)
    if args.dry_run:  # tiny models and sizes, unless given
        for name, tiny in (("models", ["pi3-tiny", "da3-tiny"]), ("compile_models", ["da3-tiny"]),
                           ("keyframes", [1, 2])):  # fmt: skip
            if getattr(args, name) == parser.get_default(name):
                setattr(args, name, tiny)
        args.session_model, args.size, args.budget, args.rounds, args.warmup = "pi3-tiny", 28, 2, 2, 1
        args.session_resolution, args.session_frames, args.session_warmup = 224, 30, 6
        args.session_interval, args.session_keyframes = 5, 4
    args.name = args.name or ("gpu_check_dry_run" if args.dry_run else "gpu_check")
    return args


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    run = Run(args)
    bodies = {"device": device_section, "peak": peak_section, "upload": upload_section,
              "parity": parity_section, "bf16": bf16_section, "steps": steps_section,
              "session": session_section, "compile": compile_section}  # fmt: skip
    for name in args.sections:
        run.section(name, bodies[name])
    print(markdown(run.result))
    return run.result


if __name__ == "__main__":
    main()

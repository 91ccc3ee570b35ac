"""Choosing the runtime, dtype and thread count by measuring them on the machine at hand.

    result = tune(open_candidate, candidates, TuneProblem(224, 224, keyframes=8), seconds=5)
    result.chosen          # Candidate("openvino", "bfloat16", 1), say
    print(result.table())  # every candidate's step time and pose deviation, and why

What is fastest depends on the CPU (bf16 matrix units or not, cores, other load) and on the
model, resolution and map size, so no fixed default is right everywhere: here it is measured.

How (the same definitions as ``benchmarks/runtimes.py``):

1. One map: ``keyframes`` synthetic frames (``synthetic_frames``: overlapping crops of one
   seeded texture) mapped by the float32 PyTorch candidate, the reference. Its poses of
   ``query_frames`` further crops are the reference poses.
2. Every candidate tracks the query frames against that map's cache, converted to its dtype (a
   bf16 cache holds the fp32 values rounded). Its pose deviation is the largest absolute
   difference of its 4x4 ``T_world_cam`` from the reference over the query frames.
3. Timing: after one untimed step each, rounds in which every candidate tracks one query frame
   (order rotated each round, so that a load spike does not hit one candidate only), until
   ``seconds`` have passed (at least ``min_rounds``); a candidate's time is its median wall time
   per step. Torch candidates that differ only in threads share one backend (``torch.
   set_num_threads`` is set before each step: the tuner owns the process while it runs). When
   all backends would not fit in half the memory available (large models), the runtimes are
   timed one after the other instead, each loaded, timed and closed before the next.
4. Choice: the fastest candidate whose deviation stays within the torch bf16 candidate's (the
   precision the project's defaults accept); fp32 candidates are within it by construction.

``open_candidate`` builds a backend for a candidate (the layer above knows how: exports for
ONNX / OpenVINO). Caching the choice per machine and model is ``io/files/tune_cache.py``'s.
"""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from kvtracker_sdk.backends.base import Backend
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.errors import BackendError, ConfigError
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.preprocess.families import for_family
from kvtracker_sdk.types import HeadSet

__all__ = [
    "RUNTIMES",
    "Candidate",
    "CandidateResult",
    "TuneProblem",
    "TuneResult",
    "default_candidates",
    "synthetic_frames",
    "tune",
]

_log = get_logger(__name__)

RUNTIMES = ("torch", "onnx", "openvino")
DTYPES = ("float32", "bfloat16")
REFERENCE_DTYPE, BOUND_DTYPE = "float32", "bfloat16"


@dataclass(frozen=True)
class Candidate:
    """One way to run the tracking step: ``runtime`` (torch, onnx, openvino), ``dtype``
    (float32, bfloat16: torch's compute dtype, OpenVINO's precision hint) and CPU ``threads``
    (None: the runtime chooses, as ONNX Runtime does)."""

    runtime: str
    dtype: str
    threads: int | None

    def __post_init__(self) -> None:
        if self.runtime not in RUNTIMES or self.dtype not in DTYPES:
            raise ConfigError(f"unknown candidate {self.runtime!r} {self.dtype!r}")
        if self.threads is not None and (isinstance(self.threads, bool) or self.threads < 1):
            raise ConfigError(f"candidate threads must be >= 1 or None, got {self.threads!r}")

    @property
    def name(self) -> str:
        threads = "auto" if self.threads is None else str(self.threads)
        return f"{self.runtime}-{'bf16' if self.dtype == 'bfloat16' else 'fp32'}-t{threads}"

    @property
    def backend_key(self) -> tuple[str, str, int | None]:
        """Candidates with one key share a backend (torch's threads change per step)."""
        return (self.runtime, self.dtype, None if self.runtime == "torch" else self.threads)


@dataclass(frozen=True)
class TuneProblem:
    """What is tuned for: a map of ``keyframes`` keyframes, tracked with ``heads``, frames of
    ``frame_size`` (H, W) pixels at the tracker's ``resolution`` (None: the family's default;
    the model input size follows from the family's preprocessing) — or ``size`` (H, W), the
    model input size itself (multiples of the patch size)."""

    keyframes: int
    resolution: int | None = None
    frame_size: tuple[int, int] = (480, 640)
    size: tuple[int, int] | None = None
    heads: HeadSet = HeadSet.CONFIDENCE

    def __post_init__(self) -> None:
        sizes = [self.keyframes, *self.frame_size, *(self.size or (1, 1)), self.resolution or 1]
        if min(sizes) < 1:
            raise ConfigError(f"tune problem needs positive sizes, got {self}")

    def model_size(self, family: str, patch_size: int) -> tuple[int, int]:
        """(H, W) of the model input, as the tracker's preprocessing makes it."""
        if self.size is not None:
            return self.size
        preprocessing = for_family(family)
        side = self.resolution or preprocessing.default_resolution
        height, width = preprocessing.model_size(self.frame_size, side, patch_size)
        return int(height), int(width)


@dataclass(frozen=True)
class CandidateResult:
    """A candidate's measurement: median and best wall seconds per step, pose deviation from
    the fp32 reference (None: it failed), whether it may be chosen, and why not."""

    candidate: Candidate
    median_s: float | None
    best_s: float | None
    steps: int
    deviation: float | None
    eligible: bool
    note: str = ""


@dataclass(frozen=True)
class TuneResult:
    """The choice and every candidate's measurement; ``reason`` says why in one line."""

    chosen: Candidate
    results: tuple[CandidateResult, ...]
    deviation_bound: float
    reason: str
    interleaved: bool
    load_average: tuple[float, float] | None  # 1-minute load at the start and the end
    seconds: float  # wall time the whole tuning took, map pass included
    extra: dict[str, Any] = field(default_factory=dict)

    def table(self) -> str:
        """A markdown table of the candidates, fastest first, the chosen one marked."""
        lines = ["| candidate | median step (s) | best (s) | steps | pose dev. | |",
                 "|---|---:|---:|---:|---:|---|"]  # fmt: skip
        timed = sorted(self.results, key=lambda r: (r.median_s is None, r.median_s or 0.0))
        for row in timed:
            mark = "chosen" if row.candidate == self.chosen else row.note
            median = "—" if row.median_s is None else f"{row.median_s:.4f}"
            best = "—" if row.best_s is None else f"{row.best_s:.4f}"
            deviation = "—" if row.deviation is None else f"{row.deviation:.1e}"
            lines.append(f"| {row.candidate.name} | {median} | {best} | {row.steps} "
                         f"| {deviation} | {mark} |")  # fmt: skip
        return "\n".join(lines)


def default_candidates(runtimes: Iterable[str], cores: int) -> list[Candidate]:
    """Each runtime in fp32 and bf16 (ONNX: fp32, its own threads) on 1 thread and on every
    usable core (and the powers of two between, on larger machines)."""
    counts = sorted({1, cores, *(2**i for i in range(1, 8) if 2**i < cores)})
    candidates: list[Candidate] = []
    for runtime in runtimes:
        if runtime == "onnx":
            candidates.append(Candidate("onnx", "float32", None))
            continue
        candidates += [Candidate(runtime, d, n) for d in DTYPES for n in counts]
    return candidates


def synthetic_frames(count: int, height: int, width: int, seed: int = 0) -> np.ndarray:
    """uint8 [count, H, W, 3]: crops of one seeded smooth texture, each shifted a little from the
    last (overlapping views of one flat scene; the step's work does not depend on the content,
    the pose deviation somewhat does)."""
    rng = np.random.default_rng(seed)
    step = max(1, min(height, width) // 32)
    cells = rng.random(((height + count * step) // 8 + 2, (width + count * step) // 8 + 2, 3))
    texture = np.kron(cells, np.ones((8, 8, 1)))  # 8-pixel blocks: structure a model can match
    texture += 0.15 * rng.standard_normal(texture.shape)
    frames = [
        texture[i * step : i * step + height, i * step : i * step + width] for i in range(count)
    ]
    return np.clip(np.stack(frames) * 255.0, 0, 255).astype(np.uint8)


# ---------------------------------------------------------------------------- measuring
@dataclass
class _Live:
    """A loaded backend, its cache (its dtype) and the candidates it serves."""

    backend: Backend
    cache: KVCache
    candidates: list[Candidate]


def _step(live: _Live, candidate: Candidate, frame: np.ndarray, heads: HeadSet) -> np.ndarray:
    if candidate.runtime == "torch" and candidate.threads is not None:
        torch.set_num_threads(candidate.threads)
    return np.asarray(live.backend.track(frame, live.cache, heads=heads).pose, dtype=np.float64)


def _backend_cache(cache: KVCache, backend: Backend) -> KVCache:
    dtype = getattr(torch, backend.info.dtype, None)
    if isinstance(dtype, torch.dtype) and dtype != cache.dtype:
        return cache.to(dtype=dtype)
    return cache


def _memory_available() -> int | None:
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def _fits_together(reference: Backend, backend_keys: Sequence[tuple[str, str, int | None]]) -> bool:
    """Whether every backend fits in half the memory available: each estimated as the fp32
    reference's parameter bytes (OpenVINO and ONNX keep fp32 weights; bf16 torch half)."""
    model = getattr(reference, "_model", None)
    if model is None:
        return False
    weights = sum(p.numel() * 4 for p in model.parameters())
    total = sum(weights // 2 if key[:2] == ("torch", "bfloat16") else weights
                for key in backend_keys)  # fmt: skip
    available = _memory_available()
    return available is not None and total <= available // 2


def _time_rounds(
    lives: Sequence[_Live], frames: np.ndarray, heads: HeadSet, seconds: float, min_rounds: int
) -> dict[Candidate, list[float]]:
    """Wall seconds per step of every candidate of ``lives``, interleaved rounds."""
    order = [(live, c) for live in lives for c in live.candidates]
    samples: dict[Candidate, list[float]] = {c: [] for _, c in order}
    for live, candidate in order:  # untimed: first-call work (static compiles, allocations)
        _step(live, candidate, frames[0], heads)
    start, rounds = time.perf_counter(), 0
    while rounds < min_rounds or (time.perf_counter() - start < seconds and rounds < 200):
        shift = rounds % len(order)
        for live, candidate in order[shift:] + order[:shift]:
            frame = frames[rounds % len(frames)]
            begin = time.perf_counter()
            _step(live, candidate, frame, heads)
            samples[candidate].append(time.perf_counter() - begin)
        rounds += 1
    return samples


def tune(
    open_candidate: Callable[[Candidate], Backend],
    candidates: Sequence[Candidate],
    problem: TuneProblem,
    *,
    seconds: float = 5.0,
    min_rounds: int = 3,
    query_frames: int = 3,
    images: np.ndarray | None = None,
    interleave: bool | None = None,
) -> TuneResult:
    """Measure ``candidates`` on ``problem`` and choose one (see the module docstring).

    ``open_candidate(candidate)`` returns a backend for it (threads as the candidate says; it is
    closed here after timing). ``images``: uint8 [keyframes + query_frames, H, W, 3] to use
    instead of ``synthetic_frames``. ``interleave``: time every candidate in the same rounds
    (None: when they fit in memory). A candidate whose backend cannot be built or fails is
    reported and skipped; ``BackendError`` when the fp32 or bf16 torch reference fails.
    """
    began, load_start = time.perf_counter(), _load()
    reference_candidate = _reference_candidate(candidates)
    threads_before = torch.get_num_threads()
    groups: dict[tuple[str, str, int | None], list[Candidate]] = {}
    for candidate in candidates:
        groups.setdefault(candidate.backend_key, []).append(candidate)
    reference = open_candidate(reference_candidate)
    height, width = problem.model_size(reference.info.family, reference.info.patch_size)
    if images is None:
        images = synthetic_frames(problem.keyframes + query_frames, height, width)
    reference_pass = _reference_pass(reference, images, problem)
    together = _fits_together(reference, list(groups)) if interleave is None else interleave
    measured = _Measurements()
    try:
        _measure_groups(open_candidate, groups, reference, reference_candidate.backend_key,
                        reference_pass, problem.heads, measured,
                        together=together, seconds=seconds, min_rounds=min_rounds)  # fmt: skip
    finally:
        for live in measured.lives:
            if live.backend is not reference:
                live.backend.close()
        reference.close()
        torch.set_num_threads(threads_before)
    result = _choose(candidates, measured.samples, measured.deviations, measured.notes, together,
                     load_start, began)  # fmt: skip
    result.extra.update(model_size=(height, width), fingerprint=reference.info.weights_fingerprint)
    return result


def _measure_groups(
    open_candidate: Callable[[Candidate], Backend],
    groups: dict[tuple[str, str, int | None], list[Candidate]],
    reference: Backend,
    reference_key: tuple[str, str, int | None],
    reference_pass: _ReferencePass,
    heads: HeadSet,
    measured: _Measurements,
    *,
    together: bool,
    seconds: float,
    min_rounds: int,
) -> None:
    """Each group's deviations, then its step times: each group on its own (its backend closed
    after), or, ``together``, every group in the same rounds (their backends left open in
    ``measured.lives`` for the caller to close). The reference backend is never closed here."""
    for key, members in groups.items():
        if key == reference_key:
            backend: Backend | None = reference
        else:
            backend = _open_group(open_candidate, key, members, measured)
        if backend is None:
            continue
        live = _Live(backend, _backend_cache(reference_pass.cache, backend), members)
        if not _measure_deviations(live, reference_pass, heads, measured):
            if backend is not reference:
                backend.close()
            continue
        if together:
            measured.lives.append(live)
        else:
            measured.samples.update(_time_rounds([live], reference_pass.queries, heads,
                                                 seconds / len(groups), min_rounds))  # fmt: skip
            if backend is not reference:
                backend.close()
    if together and measured.lives:
        measured.samples.update(
            _time_rounds(measured.lives, reference_pass.queries, heads, seconds, min_rounds)
        )


def _reference_candidate(candidates: Sequence[Candidate]) -> Candidate:
    """The torch float32 candidate (the reference poses); ConfigError without it or without a
    torch bfloat16 one (the deviation bound)."""
    reference_candidate = next((c for c in candidates if c.runtime == "torch"
                                and c.dtype == REFERENCE_DTYPE), None)  # fmt: skip
    if reference_candidate is None or not any(
        c.runtime == "torch" and c.dtype == BOUND_DTYPE for c in candidates
    ):
        raise ConfigError("the candidates must include torch float32 and torch bfloat16")
    return reference_candidate


@dataclass(frozen=True)
class _ReferencePass:
    """The reference's map of the keyframes and its poses of the query frames."""

    cache: KVCache
    queries: np.ndarray  # uint8 [Q, H, W, 3]
    poses: np.ndarray  # float64 [Q, 4, 4] T_world_cam


def _reference_pass(reference: Backend, images: np.ndarray, problem: TuneProblem) -> _ReferencePass:
    """Map ``images``' first ``problem.keyframes`` frames with the reference and track the rest."""
    keyframes, queries = images[: problem.keyframes], images[problem.keyframes :]
    if len(queries) < 1:
        raise ConfigError("tune needs at least one query frame after the keyframes")
    mapped = reference.map(keyframes)
    reference_poses = np.stack([
        np.asarray(reference.track(q, mapped.cache, heads=problem.heads).pose, np.float64)
        for q in queries
    ])  # fmt: skip
    return _ReferencePass(mapped.cache, queries, reference_poses)


@dataclass
class _Measurements:
    """What tuning found per candidate: pose deviation, step times, and why it was left out."""

    deviations: dict[Candidate, float] = field(default_factory=dict)
    samples: dict[Candidate, list[float]] = field(default_factory=dict)
    notes: dict[Candidate, str] = field(default_factory=dict)
    lives: list[_Live] = field(default_factory=list)  # backends kept open to be timed together


def _open_group(
    open_candidate: Callable[[Candidate], Backend],
    key: tuple[str, str, int | None],
    members: list[Candidate],
    measured: _Measurements,
) -> Backend | None:
    """The backend ``members`` share, or None (noted for each) when it cannot be built."""
    try:
        return open_candidate(members[0])
    except Exception as exc:  # a runtime missing or failing here: reported, skipped
        for candidate in members:
            measured.notes[candidate] = f"unavailable: {type(exc).__name__}: {exc}"[:200]
        _log.warning("tune candidate unavailable", candidate=key, error=str(exc)[:300])
        return None


def _measure_deviations(
    live: _Live, reference: _ReferencePass, heads: HeadSet, measured: _Measurements
) -> bool:
    """Record each of ``live``'s candidates' pose deviation from the reference; False (noted
    for each) when the runtime fails on a query frame."""
    try:
        for candidate in live.candidates:
            poses = np.stack([_step(live, candidate, q, heads) for q in reference.queries])
            measured.deviations[candidate] = float(np.abs(poses - reference.poses).max())
    except Exception as exc:  # noqa: BLE001 - a failing runtime is a measurement
        for candidate in live.candidates:
            measured.notes[candidate] = f"failed: {type(exc).__name__}: {exc}"[:200]
        return False
    return True


def _load() -> float | None:
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return None


def _choose(
    candidates: Sequence[Candidate],
    samples: dict[Candidate, list[float]],
    deviations: dict[Candidate, float],
    notes: dict[Candidate, str],
    interleaved: bool,
    load_start: float | None,
    began: float,
) -> TuneResult:
    """The fastest candidate within the torch bf16 deviation, and every candidate's row."""
    bound_candidates = [c for c in candidates if (c.runtime, c.dtype) == ("torch", BOUND_DTYPE)]
    bounds = [deviations[c] for c in bound_candidates if c in deviations]
    if not bounds or not any(c.dtype == REFERENCE_DTYPE and c in samples for c in candidates):
        raise BackendError(f"tuning failed: the torch references did not run ({notes})")
    bound = max(bounds)
    results = []
    for candidate in candidates:
        timed = samples.get(candidate)
        deviation = deviations.get(candidate)
        note = notes.get(candidate, "")
        within = bool(timed) and deviation is not None and deviation <= bound
        if timed and deviation is not None and deviation > bound:
            note = f"deviation {deviation:.1e} > torch bf16's {bound:.1e}"
        results.append(CandidateResult(
            candidate, statistics.median(timed) if timed else None, min(timed) if timed else None,
            len(timed or ()), deviation, within, note,
        ))  # fmt: skip
    eligible = [r for r in results if r.eligible]
    best = min(eligible, key=lambda r: r.median_s or float("inf"))
    reference = min((r for r in eligible if r.candidate.runtime == "torch"
                     and r.candidate.dtype == REFERENCE_DTYPE),
                    key=lambda r: r.median_s or float("inf"))  # fmt: skip
    assert best.median_s is not None and reference.median_s is not None
    excluded = [r.candidate.name for r in results if r.median_s is not None and not r.eligible]
    reason = (
        f"{best.candidate.name}: the fastest median step ({best.median_s:.4f} s, "
        f"{reference.median_s / best.median_s:.2f}x {reference.candidate.name}) of "
        f"{len(eligible)} candidates whose pose deviation from fp32 is within torch bf16's "
        f"({best.deviation:.1e} <= {bound:.1e})"
        + (f"; too imprecise: {', '.join(excluded)}" if excluded else "")
    )
    _log.info("tuned", chosen=best.candidate.name, reason=reason)
    return TuneResult(
        chosen=best.candidate,
        results=tuple(results),
        deviation_bound=bound,
        reason=reason,
        interleaved=interleaved,
        load_average=None if load_start is None else (load_start, _load() or 0.0),
        seconds=time.perf_counter() - began,
    )

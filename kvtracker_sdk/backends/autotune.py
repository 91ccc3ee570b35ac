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
3. Screening: after one untimed step each, rounds in which every candidate tracks one query
   frame (order rotated each round, so that a load spike does not hit one candidate only), until
   ``seconds`` have passed (at least ``min_rounds``); a candidate's screening time is its median
   wall time per step. Torch candidates that differ only in threads share one backend
   (``torch.set_num_threads`` is set before each step: the tuner owns the process while it
   runs). When all backends would not fit in half the memory available (large models), the
   runtimes are timed one after the other instead, each loaded, timed and closed before the next.
4. Racing: with a few rounds of many candidates, a median taken at different moments of a
   changing load is noise. So the eligible candidates (step 5) whose screening median, or
   fastest screening step, is within ``CONTENDER_MARGIN`` of the best one's, the contenders,
   are timed again for up to ``race_seconds`` in short rounds of only them, back to back under
   the same load, order rotated, each on the round's query frame. Each round gives every
   contender a paired ratio: its step time over the round's fastest. Load that changes between
   rounds cancels in the ratio; the contender with the lowest median ratio wins. While more
   than two race, one whose median ratio exceeds ``DROP_RATIO`` after ``DROP_AFTER_ROUNDS``
   rounds is dropped, so that the others get more rounds. Contenders of runtimes timed one
   after the other are raced only when their backends fit in memory together (loaded again);
   else the screening medians decide. A row reports its median over screening and racing.
5. Choice: among the candidates whose deviation stays within the torch bf16 candidate's (the
   precision the project's defaults accept; fp32 candidates are within it by construction), the
   race's winner; when none raced (one contender, no racing budget, not loadable together), the
   fastest screening median.

Total time: each timing phase stops at the first round that ends after its budget, so the
timing takes at most ``seconds + race_seconds`` plus one round of each phase (more only when
``min_rounds`` screening rounds take longer); loading, exports and the map pass come on top.
Every step's process CPU time is recorded too (``CandidateResult.cpu_median_s``): with other
processes on the cores it shows what the wall time includes of waiting. The choice stays on wall
time, what the user gets.

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
    "CONTENDER_MARGIN",
    "DROP_AFTER_ROUNDS",
    "DROP_RATIO",
    "Candidate",
    "CandidateResult",
    "TuneProblem",
    "TuneClock",
    "TuneResult",
    "default_candidates",
    "synthetic_frames",
    "tune",
]

_log = get_logger(__name__)

RUNTIMES = ("torch", "onnx", "openvino")
DTYPES = ("float32", "bfloat16")
# OpenVINO's per-graph precision (``openvino_runtime.MIXED``): bf16 encoder and dense heads, fp32
# decoders and camera head; a dtype of OpenVINO candidates only
MIXED = "mixed"
REFERENCE_DTYPE, BOUND_DTYPE = "float32", "bfloat16"
# Racing (module docstring, step 4). The margin is wide: under load a few screening steps can
# misorder candidates by far more than their true difference.
CONTENDER_MARGIN = 0.25  # raced: eligible screening medians within this fraction of the best
DROP_RATIO = 1.10  # while more than two race, one whose median paired ratio exceeds this ...
DROP_AFTER_ROUNDS = 5  # ... after this many racing rounds stops being timed
MAX_ROUNDS = 200  # per timing phase: bounds the rounds of very fast steps


@dataclass(frozen=True)
class TuneClock:
    """The clocks the tuner reads, in seconds: ``wall`` (what the choice is made on) and
    ``cpu``, this process's CPU time (reported only). Tests drive both."""

    wall: Callable[[], float] = field(default=time.perf_counter)
    cpu: Callable[[], float] = field(default=time.process_time)


@dataclass(frozen=True)
class Candidate:
    """One way to run the tracking step: ``runtime`` (torch, onnx, openvino), ``dtype``
    (float32, bfloat16: torch's compute dtype, OpenVINO's precision hint; for OpenVINO also
    ``MIXED``, its per-graph precision) and CPU ``threads`` (None: the runtime chooses, as ONNX
    Runtime does)."""

    runtime: str
    dtype: str
    threads: int | None

    def __post_init__(self) -> None:
        known = (*DTYPES, MIXED) if self.runtime == "openvino" else DTYPES
        if self.runtime not in RUNTIMES or self.dtype not in known:
            raise ConfigError(f"unknown candidate {self.runtime!r} {self.dtype!r}")
        if self.threads is not None and (isinstance(self.threads, bool) or self.threads < 1):
            raise ConfigError(f"candidate threads must be >= 1 or None, got {self.threads!r}")

    @property
    def name(self) -> str:
        threads = "auto" if self.threads is None else str(self.threads)
        short = {"bfloat16": "bf16", "float32": "fp32"}.get(self.dtype, self.dtype)
        return f"{self.runtime}-{short}-t{threads}"

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
    """A candidate's measurement: median and best wall seconds per step over screening and
    racing, pose deviation from the fp32 reference (None: it failed), whether it may be chosen,
    why not or how it raced, and its median process CPU seconds per step."""

    candidate: Candidate
    median_s: float | None
    best_s: float | None
    steps: int
    deviation: float | None
    eligible: bool
    note: str = ""
    cpu_median_s: float | None = None


@dataclass(frozen=True)
class TuneResult:
    """The choice and every candidate's measurement; ``reason`` says why in one line.
    ``extra["race"]``: the contenders, rounds raced, each contender's paired ratios and their
    median (None when not raced), when one was dropped and why none raced;
    ``extra["cpu_median_s"]``: per candidate."""

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
        lines = ["| candidate | median step (s) | best (s) | CPU (s) | steps | pose dev. | |",
                 "|---|---:|---:|---:|---:|---:|---|"]  # fmt: skip
        timed = sorted(self.results, key=lambda r: (r.median_s is None, r.median_s or 0.0))
        for row in timed:
            mark = "chosen" if row.candidate == self.chosen else row.note
            median = "—" if row.median_s is None else f"{row.median_s:.4f}"
            best = "—" if row.best_s is None else f"{row.best_s:.4f}"
            cpu = "—" if row.cpu_median_s is None else f"{row.cpu_median_s:.4f}"
            deviation = "—" if row.deviation is None else f"{row.deviation:.1e}"
            lines.append(f"| {row.candidate.name} | {median} | {best} | {cpu} | {row.steps} "
                         f"| {deviation} | {mark} |")  # fmt: skip
        return "\n".join(lines)


def default_candidates(runtimes: Iterable[str], cores: int) -> list[Candidate]:
    """Each runtime in fp32 and bf16 (OpenVINO also ``MIXED``; ONNX: fp32, its own threads) on
    1 thread and on every usable core (and the powers of two between, on larger machines)."""
    counts = sorted({1, cores, *(2**i for i in range(1, 8) if 2**i < cores)})
    candidates: list[Candidate] = []
    for runtime in runtimes:
        if runtime == "onnx":
            candidates.append(Candidate("onnx", "float32", None))
            continue
        dtypes = (*DTYPES, MIXED) if runtime == "openvino" else DTYPES
        candidates += [Candidate(runtime, d, n) for d in dtypes for n in counts]
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


def _timed_step(
    live: _Live,
    candidate: Candidate,
    frame: np.ndarray,
    heads: HeadSet,
    clock: TuneClock,
    measured: _Measurements,
) -> float:
    """One step of ``candidate``; its wall and CPU seconds recorded in ``measured``."""
    begin, begin_cpu = clock.wall(), clock.cpu()
    _step(live, candidate, frame, heads)
    wall = clock.wall() - begin
    measured.samples.setdefault(candidate, []).append(wall)
    measured.cpu_samples.setdefault(candidate, []).append(clock.cpu() - begin_cpu)
    return wall


def _time_rounds(
    lives: Sequence[_Live],
    frames: np.ndarray,
    heads: HeadSet,
    seconds: float,
    min_rounds: int,
    clock: TuneClock,
    measured: _Measurements,
) -> None:
    """Screening: every candidate of ``lives`` steps once per round, order rotated each round,
    until ``seconds`` have passed (at least ``min_rounds`` rounds)."""
    order = [(live, c) for live in lives for c in live.candidates]
    for live, candidate in order:  # untimed: first-call work (static compiles, allocations)
        _step(live, candidate, frames[0], heads)
    start, rounds = clock.wall(), 0
    while rounds < min_rounds or (clock.wall() - start < seconds and rounds < MAX_ROUNDS):
        shift = rounds % len(order)
        for live, candidate in order[shift:] + order[:shift]:
            _timed_step(live, candidate, frames[rounds % len(frames)], heads, clock, measured)
        rounds += 1


def tune(
    open_candidate: Callable[[Candidate], Backend],
    candidates: Sequence[Candidate],
    problem: TuneProblem,
    *,
    seconds: float = 5.0,
    race_seconds: float | None = None,
    min_rounds: int = 3,
    query_frames: int = 3,
    images: np.ndarray | None = None,
    interleave: bool | None = None,
    clock: TuneClock | None = None,
) -> TuneResult:
    """Measure ``candidates`` on ``problem`` and choose one (see the module docstring).

    ``open_candidate(candidate)`` returns a backend for it (threads as the candidate says; it is
    closed here after timing). ``seconds``: the screening budget; ``race_seconds``: the budget
    for racing the contenders (None: ``seconds`` again; 0: no racing, the screening medians
    decide). ``images``: uint8 [keyframes + query_frames, H, W, 3] to use instead of
    ``synthetic_frames``. ``interleave``: time every candidate in the same rounds (None: when
    they fit in memory). ``clock``: the clocks read (None: ``time.perf_counter`` and
    ``time.process_time``). A candidate whose backend cannot be built or fails is reported and
    skipped; ``BackendError`` when the fp32 or bf16 torch reference fails.
    """
    race_seconds = _race_budget(seconds, race_seconds)
    clock = clock or TuneClock()
    began, load_start = clock.wall(), _load()
    reference_candidate = _reference_candidate(candidates)
    threads_before = torch.get_num_threads()
    groups = _backend_groups(candidates)
    reference = open_candidate(reference_candidate)
    height, width = problem.model_size(reference.info.family, reference.info.patch_size)
    if images is None:
        images = synthetic_frames(problem.keyframes + query_frames, height, width)
    reference_pass = _reference_pass(reference, images, problem)
    together = _fits_together(reference, list(groups)) if interleave is None else interleave
    measured = _Measurements()
    session = _Session(open_candidate, reference, reference_candidate.backend_key,
                       reference_pass, _Timing(reference_pass.queries, problem.heads, clock),
                       measured)  # fmt: skip
    try:
        _measure_groups(session, groups, together=together, seconds=seconds,
                        min_rounds=min_rounds)  # fmt: skip
        bound = _deviation_bound(candidates, measured)
        race = _Race(_contenders(candidates, measured, bound))
        if len(race.contenders) > 1 and race_seconds > 0:
            _race(session, race, together=together, seconds=race_seconds)
    finally:
        for live in measured.lives:
            if live.backend is not reference:
                live.backend.close()
        reference.close()
        torch.set_num_threads(threads_before)
    result = _choose(candidates, measured, bound, race, together, load_start,
                     clock.wall() - began)  # fmt: skip
    result.extra.update(model_size=(height, width), fingerprint=reference.info.weights_fingerprint)
    return result


def _race_budget(seconds: float, race_seconds: float | None) -> float:
    """The racing budget (None: ``seconds`` again); ``ConfigError`` for a negative or NaN one."""
    race_seconds = seconds if race_seconds is None else race_seconds
    if not (seconds >= 0 and race_seconds >= 0):  # also rejects NaN
        raise ConfigError(f"tune budgets must be >= 0 s, got {seconds!r} and {race_seconds!r}")
    return race_seconds


def _backend_groups(
    candidates: Sequence[Candidate],
) -> dict[tuple[str, str, int | None], list[Candidate]]:
    """The candidates by the backend they share (``Candidate.backend_key``), in order."""
    groups: dict[tuple[str, str, int | None], list[Candidate]] = {}
    for candidate in candidates:
        groups.setdefault(candidate.backend_key, []).append(candidate)
    return groups


@dataclass(frozen=True)
class _Timing:
    """What every timed step uses: the query frames (uint8 [Q, H, W, 3]), heads and clocks."""

    frames: np.ndarray
    heads: HeadSet
    clock: TuneClock


@dataclass(frozen=True)
class _Session:
    """What the measuring phases share: the opener, the reference backend (its group's key and
    its pass) and the timing, and where the measurements go."""

    open_candidate: Callable[[Candidate], Backend]
    reference: Backend
    reference_key: tuple[str, str, int | None]
    reference_pass: _ReferencePass
    timing: _Timing
    measured: _Measurements

    def live(self, backend: Backend, members: list[Candidate]) -> _Live:
        """``backend`` serving ``members`` with the reference map's cache in its dtype."""
        return _Live(backend, _backend_cache(self.reference_pass.cache, backend), members)

    def close(self, backend: Backend) -> None:
        """Close ``backend`` unless it is the reference (closed by ``tune`` at the end)."""
        if backend is not self.reference:
            backend.close()


def _measure_groups(
    session: _Session,
    groups: dict[tuple[str, str, int | None], list[Candidate]],
    *,
    together: bool,
    seconds: float,
    min_rounds: int,
) -> None:
    """Each group's deviations, then its screening step times: each group on its own (its
    backend closed after), or, ``together``, every group in the same rounds (their backends left
    open in ``measured.lives`` for the caller to close). The reference backend is never closed
    here."""
    timing, measured = session.timing, session.measured
    for key, members in groups.items():
        if key == session.reference_key:
            backend: Backend | None = session.reference
        else:
            backend = _open_group(session.open_candidate, key, members, measured)
        if backend is None:
            continue
        live = session.live(backend, members)
        if not _measure_deviations(live, session.reference_pass, timing.heads, measured):
            session.close(backend)
            continue
        if together:
            measured.lives.append(live)
        else:
            _time_rounds([live], timing.frames, timing.heads, seconds / len(groups), min_rounds,
                         timing.clock, measured)  # fmt: skip
            session.close(backend)
    if together and measured.lives:
        _time_rounds(measured.lives, timing.frames, timing.heads, seconds, min_rounds,
                     timing.clock, measured)  # fmt: skip


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
    samples: dict[Candidate, list[float]] = field(default_factory=dict)  # wall s per step
    cpu_samples: dict[Candidate, list[float]] = field(default_factory=dict)  # process CPU s
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


# ---------------------------------------------------------------------------- racing
@dataclass
class _Race:
    """The contenders and what racing them found: per contender its paired ratios (its step
    time over the fastest contender's in the same round) and the round after which it was
    dropped. ``rounds`` 0: not raced (one contender, no budget, or not loadable together)."""

    contenders: list[Candidate]
    ratios: dict[Candidate, list[float]] = field(default_factory=dict)
    dropped_after: dict[Candidate, int] = field(default_factory=dict)
    rounds: int = 0
    not_raced_why: str = ""

    def median_ratio(self, candidate: Candidate) -> float | None:
        ratios = self.ratios.get(candidate)
        return statistics.median(ratios) if ratios else None

    def record(self) -> dict[str, Any]:
        """What ``TuneResult.extra["race"]`` holds (JSON-ready: candidates by name)."""
        return {
            "contenders": [c.name for c in self.contenders],
            "margin": CONTENDER_MARGIN,
            "rounds": self.rounds,
            "median_ratio": {c.name: self.median_ratio(c) for c in self.contenders},
            "ratios": {c.name: self.ratios.get(c, []) for c in self.contenders},
            "dropped_after": {c.name: n for c, n in self.dropped_after.items()},
            "not_raced": self.not_raced_why,
        }


def _eligible(candidate: Candidate, measured: _Measurements, bound: float) -> bool:
    deviation = measured.deviations.get(candidate)
    return bool(measured.samples.get(candidate)) and deviation is not None and deviation <= bound


def _deviation_bound(candidates: Sequence[Candidate], measured: _Measurements) -> float:
    """The torch bf16 candidates' largest deviation; BackendError when the references failed."""
    bounds = [measured.deviations[c] for c in candidates
              if (c.runtime, c.dtype) == ("torch", BOUND_DTYPE) and c in measured.deviations]  # fmt: skip
    if not bounds or not any(c.dtype == REFERENCE_DTYPE and c in measured.samples
                             for c in candidates):  # fmt: skip
        raise BackendError(f"tuning failed: the torch references did not run ({measured.notes})")
    return max(bounds)


def _contenders(
    candidates: Sequence[Candidate], measured: _Measurements, bound: float
) -> list[Candidate]:
    """The eligible candidates whose screening median, or fastest screening step, is within
    ``CONTENDER_MARGIN`` of the best eligible one's (in ``candidates``' order)."""
    eligible = [c for c in candidates if _eligible(c, measured, bound)]
    if not eligible:
        raise BackendError("tuning failed: no candidate within the torch bf16 deviation ran")
    medians = {c: statistics.median(measured.samples[c]) for c in eligible}
    # Other load only ever slows a step, so a candidate's fastest step is its least disturbed:
    # one whose few steps mostly fell into busy moments still gets into the race by it.
    fastest = {c: min(measured.samples[c]) for c in eligible}
    within = 1.0 + CONTENDER_MARGIN
    best_median, best_fastest = min(medians.values()), min(fastest.values())
    return [c for c in eligible
            if medians[c] <= best_median * within or fastest[c] <= best_fastest * within]  # fmt: skip


def _race(session: _Session, race: _Race, *, together: bool, seconds: float) -> None:
    """Time ``race.contenders`` in rounds of only them for up to ``seconds``. Their backends are
    still open when ``together``; else they are loaded again (added to ``measured.lives`` for
    the caller to close) when they fit in memory together, and not raced when they do not."""
    timing, measured = session.timing, session.measured
    if together:
        entrants = [(live, c) for live in measured.lives for c in live.candidates
                    if c in race.contenders]  # fmt: skip
    else:
        keys = list(dict.fromkeys(c.backend_key for c in race.contenders))
        if len(keys) > 1 and not _fits_together(session.reference, keys):
            race.not_raced_why = "their runtimes do not fit in memory together"
            return
        entrants = []
        for key in keys:
            members = [c for c in race.contenders if c.backend_key == key]
            try:
                backend = (session.reference if key == session.reference_key
                           else session.open_candidate(members[0]))  # fmt: skip
            except Exception as exc:  # built once already; if not again, race the others
                _log.warning("tune contender unavailable", candidate=key, error=str(exc)[:300])
                continue
            live = session.live(backend, members)
            if backend is not session.reference:
                measured.lives.append(live)
            for candidate in members:  # untimed: first-call work again
                _step(live, candidate, timing.frames[0], timing.heads)
            entrants += [(live, c) for c in members]
        if len(entrants) < 2:
            race.not_raced_why = "the contenders' backends could not be loaded again"
            return
    _race_rounds(entrants, race, timing, measured, seconds)


def _race_rounds(
    entrants: list[tuple[_Live, Candidate]],
    race: _Race,
    timing: _Timing,
    measured: _Measurements,
    seconds: float,
) -> None:
    """Rounds of the ``entrants`` still in the race (order rotated, every one on the round's
    frame), each giving every entrant its paired ratio, until ``seconds`` have passed or one is
    left; from ``DROP_AFTER_ROUNDS`` on, the clearly slower leave (``_drop_the_clearly_slower``)."""
    active = list(entrants)
    start = timing.clock.wall()
    while len(active) > 1 and race.rounds < MAX_ROUNDS and timing.clock.wall() - start < seconds:
        shift = race.rounds % len(active)
        frame = timing.frames[race.rounds % len(timing.frames)]
        walls = {c: _timed_step(live, c, frame, timing.heads, timing.clock, measured)
                 for live, c in active[shift:] + active[:shift]}  # fmt: skip
        fastest = max(min(walls.values()), 1e-12)  # a clock that did not move: no division by 0
        for candidate, wall in walls.items():
            race.ratios.setdefault(candidate, []).append(wall / fastest)
        race.rounds += 1
        if race.rounds >= DROP_AFTER_ROUNDS:
            _drop_the_clearly_slower(active, race)


def _drop_the_clearly_slower(active: list[tuple[_Live, Candidate]], race: _Race) -> None:
    """Remove from ``active`` the slowest ones whose median ratio exceeds ``DROP_RATIO``, while
    more than two are left: dropping is for giving the others more rounds, and the last two
    race to the end (the lowest median ratio is never dropped)."""
    medians = {c: statistics.median(race.ratios[c]) for _, c in active}
    for candidate in sorted(medians, key=medians.__getitem__, reverse=True):
        if len(active) <= 2 or medians[candidate] <= DROP_RATIO:
            return
        active[:] = [entry for entry in active if entry[1] != candidate]
        race.dropped_after[candidate] = race.rounds


# ---------------------------------------------------------------------------- choosing
def _choose(
    candidates: Sequence[Candidate],
    measured: _Measurements,
    bound: float,
    race: _Race,
    interleaved: bool,
    load_start: float | None,
    seconds: float,
) -> TuneResult:
    """Every candidate's row and the choice: the race's winner among the contenders, else the
    fastest screening median within the torch bf16 deviation."""
    results = []
    for candidate in candidates:
        timed = measured.samples.get(candidate)
        cpu = measured.cpu_samples.get(candidate)
        deviation = measured.deviations.get(candidate)
        note = measured.notes.get(candidate, "")
        if timed and deviation is not None and deviation > bound:
            note = f"deviation {deviation:.1e} > torch bf16's {bound:.1e}"
        ratio = race.median_ratio(candidate)
        if ratio is not None:
            rounds = race.dropped_after.get(candidate, race.rounds)
            note = (f"raced: median {ratio:.2f}x the round's fastest in {rounds} paired rounds"
                    + (" (dropped)" if candidate in race.dropped_after else ""))  # fmt: skip
        results.append(CandidateResult(
            candidate, statistics.median(timed) if timed else None, min(timed) if timed else None,
            len(timed or ()), deviation, _eligible(candidate, measured, bound), note,
            statistics.median(cpu) if cpu else None,
        ))  # fmt: skip
    rows = {r.candidate: r for r in results}
    eligible = [r for r in results if r.eligible]
    if race.rounds:
        best = rows[min((c for c in race.contenders if race.median_ratio(c) is not None),
                        key=lambda c: (race.median_ratio(c), rows[c].median_s))]  # fmt: skip
    else:  # not raced: the whole-run medians are the screening medians
        best = min(eligible, key=lambda r: r.median_s or float("inf"))
    reference = min((r for r in eligible if r.candidate.runtime == "torch"
                     and r.candidate.dtype == REFERENCE_DTYPE),
                    key=lambda r: r.median_s or float("inf"))  # fmt: skip
    assert best.median_s is not None and reference.median_s is not None
    reason = _reason(best, reference, race, results, bound)
    _log.info("tuned", chosen=best.candidate.name, reason=reason)
    return TuneResult(
        chosen=best.candidate,
        results=tuple(results),
        deviation_bound=bound,
        reason=reason,
        interleaved=interleaved,
        load_average=None if load_start is None else (load_start, _load() or 0.0),
        seconds=seconds,
        extra={"race": race.record(),
               "cpu_median_s": {r.candidate.name: r.cpu_median_s for r in results}},  # fmt: skip
    )


def _reason(
    best: CandidateResult,
    reference: CandidateResult,
    race: _Race,
    results: Sequence[CandidateResult],
    bound: float,
) -> str:
    """One line: how ``best`` was chosen, and which candidates were too imprecise."""
    assert best.median_s is not None and reference.median_s is not None
    eligible = sum(r.eligible for r in results)
    speed = (f"{best.median_s:.4f} s, {reference.median_s / best.median_s:.2f}x "
             f"{reference.candidate.name}")  # fmt: skip
    if race.rounds:
        ratio = race.median_ratio(best.candidate)
        others = ", ".join(f"{c.name} {race.median_ratio(c):.2f}x"
                           + (" (dropped)" if c in race.dropped_after else "")
                           for c in race.contenders
                           if c != best.candidate and race.median_ratio(c) is not None)  # fmt: skip
        how = (
            f"chosen by {race.rounds} paired rounds among {len(race.contenders)} contenders "
            f"(screening median or fastest step within {CONTENDER_MARGIN:.0%} of the best): median "
            f"{ratio:.2f}x the round's fastest vs {others or 'none raced'}; median step {speed}"
        )
    else:
        why_not = race.not_raced_why
        if not why_not:
            alone = len(race.contenders) < 2
            why_not = f"no other within {CONTENDER_MARGIN:.0%}" if alone else "no racing budget"
        how = f"the fastest median step ({speed}), not raced: {why_not}"
    excluded = [r.candidate.name for r in results if r.median_s is not None and not r.eligible]
    return (
        f"{best.candidate.name}: {how}; among {eligible} candidates whose pose deviation from "
        f"fp32 is within torch bf16's ({best.deviation:.1e} <= {bound:.1e})"
        + (f"; too imprecise: {', '.join(excluded)}" if excluded else "")
    )

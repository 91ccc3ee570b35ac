"""Opt-in ``torch.compile`` of the tracking step: ``TorchBackend(..., compile=CompileOptions())``.

    backend = TorchBackend.from_pretrained("da3-small", dtype="bfloat16", compile=True)
    backend.track(frame, cache)             # the first call compiles (about a minute on a 2-core CPU)
    backend.compile_report                  # CompileReport(status="compiled", first_call_s=68.4, ...)

What is compiled: the model's ``forward_track`` (encoder, the blocks with their cache reads and
scratch writes, the requested heads) with TorchInductor. With ``freezing`` (default) the weights
become constants of the compiled graph, so Inductor folds them and pre-packs the matrix products'
weights for oneDNN; the backend owns its model, so the weights never change under it. Mapping stays
eager (it runs rarely and on varying keyframe counts).

Compilation happens on the first call and again for every new frame size or keyframe count: the
cache length is a Python int (it slices the cache), so Dynamo specialises on it. A map that grows
recompiles once per count (a few seconds per count for a tiny model with a warm cache, minutes cold
for a real one); past torch's recompile limit (``torch._dynamo.config.recompile_limit``, 8) further
counts run eager. The compiled path therefore pays off for fixed maps (relocalisation against a
saved map, a map that is rebuilt rarely) more than for a map that grows every few frames.
Inductor keeps its compiled kernels and FX graphs in ``$TORCHINDUCTOR_CACHE_DIR``, which this module
sets, unless it is set, to ``CompileOptions.cache_dir`` or ``<user cache>/kvtracker_sdk/inductor``
(``$KVTRACKER_CACHE_DIR/inductor`` when that is set): a later process with the same model and shapes
reuses them. Dynamo still traces the model in every process, so the first call is shorter, not free
(figures: ``benchmarks/README.md#figures-behind-the-code``).

Results differ from eager by the reordering of floating-point sums (fused kernels): the runtimes
benchmark measures the pose difference (``benchmarks/runtimes.py``). Without a usable compiler
(``compile_unavailable_reason``) or when compilation fails, ``CompileError`` is raised — or, with
``fallback=True``, the step runs eager and ``compile_report.status`` says why.
"""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import torch
from torch import nn

from kvtracker_sdk.errors import CompileError, ConfigError, KVTrackerError
from kvtracker_sdk.log import get_logger

__all__ = [
    "CompileOptions",
    "CompileReport",
    "CompiledTracking",
    "compile_unavailable_reason",
    "inductor_cache_dir",
]

_log = get_logger(__name__)


@dataclass(frozen=True)
class CompileOptions:
    """How the tracking step is compiled (``torch.compile`` arguments, plus where to cache)."""

    backend: str = "inductor"  # "eager" / "aot_eager": Dynamo only (debugging, cheap tests)
    mode: str | None = None  # torch.compile mode, e.g. "max-autotune" (long compile)
    freezing: bool = True  # Inductor folds the weights as constants (inductor backend only)
    dynamic: bool | None = None  # None: static first, dynamic after a shape changes
    cache_dir: Path | None = None  # Inductor's cache; None: ``inductor_cache_dir()``
    fallback: bool = False  # True: run eager (and report why) when compiling is impossible

    def describe(self) -> str:
        """Short name for ``BackendInfo.accelerations``, e.g. ``torch.compile-inductor-freezing``."""
        parts = ["torch.compile", self.backend]
        if self.freezing and self.backend == "inductor":
            parts.append("freezing")
        if self.mode:
            parts.append(self.mode)
        return "-".join(parts)


@dataclass
class CompileReport:
    """What happened to the compilation: ``status`` is "pending" (not called yet), "compiled", or
    "eager: <reason>" (fallback); ``first_call_s`` the first call's seconds (compile + one step)."""

    options: CompileOptions
    status: str = "pending"
    first_call_s: float | None = None
    cache_dir: Path | None = None
    errors: list[str] = field(default_factory=list)


def inductor_cache_dir(options: CompileOptions | None = None) -> Path:
    """Inductor's cache folder: ``options.cache_dir``, else ``$TORCHINDUCTOR_CACHE_DIR``, else
    ``$KVTRACKER_CACHE_DIR/inductor``, else ``$XDG_CACHE_HOME`` (or ``~/.cache``)
    ``/kvtracker_sdk/inductor``."""
    if options is not None and options.cache_dir is not None:
        return Path(options.cache_dir)
    if chosen := os.environ.get("TORCHINDUCTOR_CACHE_DIR"):
        return Path(chosen)
    if root := os.environ.get("KVTRACKER_CACHE_DIR"):
        return Path(root) / "inductor"
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "kvtracker_sdk" / "inductor"


def compile_unavailable_reason(options: CompileOptions) -> str | None:
    """Why ``torch.compile`` cannot run here with ``options`` (None: it can, as far as can be told
    without compiling): Dynamo unsupported on this Python, or Inductor on CPU without a C++
    compiler (``$CXX``, else ``g++``)."""
    import torch._dynamo

    if not torch._dynamo.is_dynamo_supported():
        return f"torch.compile does not support this Python/platform (torch {torch.__version__})"
    if options.backend == "inductor":
        compiler = os.environ.get("CXX") or "g++"
        if shutil.which(compiler) is None:
            return f"Inductor needs a C++ compiler for CPU kernels and {compiler!r} is not on PATH"
    return None


class CompiledTracking:
    """``model.forward_track`` compiled per ``options`` (same signature, same outputs up to float
    reordering). Construction raises ``CompileError`` when compiling is impossible and
    ``options.fallback`` is False; calls raise it when compilation fails (or fall back)."""

    def __init__(self, model: nn.Module, options: CompileOptions) -> None:
        if options.freezing and options.backend != "inductor":
            raise ConfigError(f"freezing needs the inductor backend, not {options.backend!r}")
        self._eager: Any = cast(Any, model).forward_track
        self.report = CompileReport(options)
        self._compiled: Any = None
        if options.backend == "inductor":
            # process-wide, and before Dynamo loads: Inductor reads the variable, and fills in its
            # own default (under /tmp) when it finds none. An explicit cache_dir wins; otherwise a
            # choice made before (the caller's, or torch's own in this process) is kept.
            if options.cache_dir is not None:
                os.environ["TORCHINDUCTOR_CACHE_DIR"] = str(options.cache_dir)
            else:
                os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(inductor_cache_dir()))
            self.report.cache_dir = Path(os.environ["TORCHINDUCTOR_CACHE_DIR"])
        reason = compile_unavailable_reason(options)
        if reason is not None:
            self._fall_back(reason)
            return
        self._compiled = torch.compile(
            self._eager,
            backend=options.backend,
            mode=options.mode,
            dynamic=options.dynamic,
            options={"freezing": True} if options.freezing else None,
        )

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        if self._compiled is None:
            return self._eager(*args, **kwargs)
        start = time.perf_counter()
        try:
            output = self._compiled(*args, **kwargs)
        except KVTrackerError:
            raise  # the model's own checks (cache layout, image shape): not a compile failure
        except Exception as exc:  # Dynamo/Inductor raise many types; all mean "did not compile"
            self._fall_back(f"compilation failed: {type(exc).__name__}: {exc}", exc)
            return self._eager(*args, **kwargs)
        if self.report.first_call_s is None:
            self.report.first_call_s = time.perf_counter() - start
            self.report.status = "compiled"
            _log.info(
                "tracking step compiled",
                options=self.report.options.describe(),
                first_call_s=round(self.report.first_call_s, 2),
                cache_dir=str(self.report.cache_dir),
            )
        return output

    def _fall_back(self, reason: str, cause: BaseException | None = None) -> None:
        self.report.errors.append(reason)
        if not self.report.options.fallback:
            raise CompileError(
                f"cannot compile the tracking step: {reason} (CompileOptions(fallback=True) runs "
                "it eager instead)"
            ) from cause
        self._compiled = None
        self.report.status = f"eager: {reason}"
        _log.warning("torch.compile unavailable, tracking runs eager", reason=reason)

"""A backend by kind and weights: ``open_backend("onnx", "pi3_onnx/")`` or a ``BackendSpec``.

What ``kvtracker track --backend/--weights/--dtype/--device/--threads``, ``eval-many`` (its
manifest names a backend per config), the tracker service and an app all call, so that a name
means the same runtime everywhere.

Each runtime is imported only when chosen: the PyTorch backend loads the checkpoint (a
``.safetensors`` file, a folder holding one, or a hub id such as ``yyfz233/Pi3``); the ONNX and
OpenVINO backends load exported graphs (``kvtracker export-onnx``) from ``weights``, or export
a checkpoint there once. OpenVINO takes ``dtype="bfloat16"`` as its precision hint (its cache
stays float32), and ``dtype="mixed"``, its per-graph precision (bf16 encoder and dense heads,
fp32 decoders and camera head; ``backends/openvino_runtime.py``), which only it has. ``threads``: torch's intra-op threads (process-wide), ONNX Runtime's intra-op
threads, OpenVINO's inference threads; None lets each runtime choose.

``options`` are the runtime's own keyword arguments, checked against the ones it takes:

| kind | options |
|---|---|
| torch | ``compile`` (bool), ``attention`` (``"sdpa"`` ...), ``model_name`` |
| onnx | ``providers`` (ONNX Runtime execution providers), ``cache_dir`` (where a checkpoint is exported) |
| openvino | ``static_shapes`` (bool or graph names), ``cache_dir`` |
"""

from __future__ import annotations

import enum
import importlib
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from kvtracker_sdk.errors import ConfigError, MissingDependencyError

if TYPE_CHECKING:
    from kvtracker_sdk.backends.base import Backend

__all__ = [
    "DEFAULT_WEIGHTS",
    "RUNTIME_OPTIONS",
    "BackendKind",
    "BackendSpec",
    "ComputeDtype",
    "open_backend",
]

DEFAULT_WEIGHTS = "yyfz233/Pi3"  # the official Pi3 checkpoint on the Hugging Face hub


class BackendKind(str, enum.Enum):
    AUTO = "auto"  # resolved by cli/tune.py's auto_choice before a backend is opened
    TORCH = "torch"
    ONNX = "onnx"
    OPENVINO = "openvino"


class ComputeDtype(str, enum.Enum):
    FLOAT32 = "float32"
    BFLOAT16 = "bfloat16"
    MIXED = "mixed"  # OpenVINO's per-graph precision only (the module docstring)


# the keyword arguments each runtime's constructor takes besides weights, device, dtype, threads
RUNTIME_OPTIONS: dict[BackendKind, frozenset[str]] = {
    BackendKind.TORCH: frozenset({"compile", "attention", "model_name"}),
    BackendKind.ONNX: frozenset({"providers", "cache_dir"}),
    BackendKind.OPENVINO: frozenset({"static_shapes", "cache_dir"}),
}


class BackendSpec(BaseModel):
    """A backend as plain data (what a manifest holds and a task ships to a worker):
    ``BackendSpec(kind="onnx", weights="pi3_onnx/").open()``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: BackendKind = BackendKind.TORCH
    weights: str = DEFAULT_WEIGHTS  # a checkpoint (file, folder, hub id) or an export folder
    dtype: ComputeDtype = ComputeDtype.FLOAT32
    device: str = "cpu"
    threads: int | None = Field(default=None, ge=1)
    options: dict[str, Any] = Field(default_factory=dict)

    @classmethod
    def of(cls, data: BackendSpec | dict[str, Any]) -> BackendSpec:
        """A spec from a dict (ConfigError naming the bad field) or a spec as it is."""
        if isinstance(data, BackendSpec):
            return data
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise ConfigError(f"backend {data!r}: {exc}") from exc

    def open(self, *, threads: int | None = None) -> Backend:
        """The backend; ``threads`` stands in when the spec sets none."""
        return open_backend(
            self.kind, self.weights, device=self.device, dtype=self.dtype,
            threads=self.threads if self.threads is not None else threads, options=self.options,
        )

    def label(self) -> str:
        """``kind/dtype`` (``torch/float32``): how a results table names the runtime."""
        return f"{self.kind.value}/{self.dtype.value}"


def _check_request(kind: BackendKind, dtype_name: str, threads: int | None) -> None:
    """``ConfigError`` for a request no runtime takes: threads below 1, ``auto`` (resolved
    before a backend opens), ``mixed`` outside OpenVINO."""
    if threads is not None and threads < 1:
        raise ConfigError(f"--threads must be >= 1, got {threads}")
    if kind is BackendKind.AUTO:
        raise ConfigError("backend 'auto' is resolved by `kvtracker tune`'s choice before a "
                          "backend opens: name torch, onnx or openvino here")
    if dtype_name == ComputeDtype.MIXED.value and kind is not BackendKind.OPENVINO:
        raise ConfigError(f"dtype 'mixed' is OpenVINO's per-graph precision; the {kind.value} "
                          "backend takes float32 or bfloat16 (PyTorch's bf16 keeps its residual "
                          "stream in fp32 already)")


def open_backend(
    kind: BackendKind | str,
    weights: str | Path,
    *,
    device: str = "cpu",
    dtype: ComputeDtype | str = "float32",
    threads: int | None = None,
    options: dict[str, Any] | None = None,
    on_export: Callable[[Path], None] | None = None,
) -> Backend:
    """The backend of ``kind`` over ``weights``; typed errors for an unknown kind or option,
    missing runtimes or weights (see the module docstring). ``on_export(folder)``: called when a
    checkpoint is about to be exported for the ONNX or OpenVINO backend (not when its cached
    export is reused)."""
    try:
        kind = BackendKind(kind)
        dtype_name = ComputeDtype(dtype).value
    except ValueError as exc:
        raise ConfigError(f"backend {kind!r} / dtype {dtype!r}: {exc}") from exc
    _check_request(kind, dtype_name, threads)
    extra = dict(options or {})
    unknown = sorted(set(extra) - RUNTIME_OPTIONS[kind])
    if unknown:
        raise ConfigError(f"the {kind.value} backend takes no option {unknown} "
                          f"(it takes {sorted(RUNTIME_OPTIONS[kind])})")
    if kind is BackendKind.TORCH:
        try:
            from kvtracker_sdk.backends.torch_backend import TorchBackend
        except ImportError as exc:
            raise MissingDependencyError(f"the PyTorch backend cannot be imported: {exc}") from exc
        # None: the backend chooses from the free cores (kvtracker_sdk/threads.py)
        return TorchBackend.from_pretrained(
            weights, dtype=dtype_name, device=device, threads=threads, **extra
        )
    if kind is BackendKind.ONNX:
        if dtype_name != ComputeDtype.FLOAT32.value:
            raise ConfigError("the ONNX backend runs the exported graphs' dtype; drop --dtype")
        try:
            module = importlib.import_module("kvtracker_sdk.export_onnx.reuse")
        except ImportError as exc:
            raise MissingDependencyError.for_extra(
                "onnx", f"the ONNX backend needs onnxruntime ({exc})") from exc
        backend: Backend = module.onnx_backend(weights, device=device, threads=threads,
                                               on_export=on_export, **extra)
        return backend
    try:  # openvino itself is imported when the backend is made (MissingDependencyError)
        module = importlib.import_module("kvtracker_sdk.export_onnx.reuse")
    except ImportError as exc:
        raise MissingDependencyError.for_extra(
            "openvino", f"the OpenVINO backend cannot be imported ({exc})") from exc
    served: Backend = module.openvino_backend(
        weights, device=device, precision=dtype_name, threads=threads, on_export=on_export,
        **extra
    )
    return served

"""ONNX Runtime sessions of an export folder, chained into mapping and tracking passes.

``OnnxRunner`` is the ``GraphRunner`` (``graph_runner``: the passes, in numpy) whose graphs run
as ONNX Runtime sessions.

Speed choices (``session_options``): full graph optimisation (``ORT_ENABLE_ALL``: fusions of
LayerNorm, GELU, MatMul+Add...), the CPU memory arena and memory patterns (buffers are reused
from one step to the next), sequential execution with ``threads`` intra-op threads (one
transformer block at a time: there is no parallelism between nodes worth a second pool).
Inputs are passed as numpy arrays, which ONNX Runtime reads in place when they are C-contiguous
(a 1.2 GB cache buffer costs microseconds to bind), so no I/O binding is needed on CPU.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kvtracker_sdk.backends.graph_runner import GraphRunner
from kvtracker_sdk.backends.onnx_claims import check_graph_signatures
from kvtracker_sdk.backends.onnx_manifest import OnnxManifest
from kvtracker_sdk.errors import BackendError, ConfigError, MissingDependencyError

__all__ = ["OnnxRunner", "import_onnxruntime", "providers_for", "session_options"]

def import_onnxruntime() -> Any:
    """The ``onnxruntime`` module, or ``MissingDependencyError`` naming the ``[onnx]`` extra."""
    try:
        return importlib.import_module("onnxruntime")
    except ImportError as exc:
        raise MissingDependencyError.for_extra(
            "onnx", f"the ONNX backend needs onnxruntime ({exc})") from exc


# SDK device name -> the execution provider serving it (CPU stays listed as the fallback)
_DEVICE_PROVIDERS = {
    "cpu": "CPUExecutionProvider",
    "cuda": "CUDAExecutionProvider",
    "coreml": "CoreMLExecutionProvider",
    "directml": "DmlExecutionProvider",
}


def providers_for(device: str = "cpu", providers: Sequence[Any] | None = None) -> list[Any]:
    """The provider list for ``device`` ("cpu", "cuda[:N]", "coreml", "directml"), or the
    explicit ``providers`` (names or (name, options) pairs, as onnxruntime takes them).

    ``MissingDependencyError`` when this onnxruntime build lacks one of them (e.g. CUDA needs
    the ``onnxruntime-gpu`` package).
    """
    if providers is None:
        kind, _, index = device.partition(":")
        if kind not in _DEVICE_PROVIDERS or (index and not index.isdigit()):
            raise ConfigError(f"unknown ONNX device {device!r}; expected one of {sorted(_DEVICE_PROVIDERS)}")
        providers = ["CPUExecutionProvider"]
        if kind != "cpu":
            options = {"device_id": int(index)} if index else {}
            providers.insert(0, (_DEVICE_PROVIDERS[kind], options))
    available = import_onnxruntime().get_available_providers()
    names = [p if isinstance(p, str) else p[0] for p in providers]
    missing = [name for name in names if name not in available]
    if missing:
        raise MissingDependencyError(
            f"this onnxruntime build has no {missing} (available: {available}); install the "
            "onnxruntime package built for that device (e.g. onnxruntime-gpu for CUDA)"
        )
    return list(providers)


def session_options(threads: int | None = None) -> Any:
    """Session options tuned for a tracking loop (see the module docstring)."""
    ort = import_onnxruntime()
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.intra_op_num_threads = threads or 0  # 0: one per physical core
    options.inter_op_num_threads = 1
    options.enable_cpu_mem_arena = True
    options.enable_mem_pattern = True
    options.log_severity_level = 4  # fatal only: failures reach the caller as BackendError
    return options


class OnnxRunner(GraphRunner):
    """One ONNX Runtime session per graph of an export; mapping and tracking passes in numpy."""

    def __init__(
        self,
        folder: str | Path,
        manifest: OnnxManifest,
        *,
        providers: Sequence[Any] | None = None,
        threads: int | None = None,
    ) -> None:
        super().__init__(manifest)
        ort = import_onnxruntime()
        folder = Path(folder)
        self.providers = providers_for("cpu", providers)
        options = session_options(threads)
        try:
            self._sessions = {
                name: ort.InferenceSession(
                    str(folder / spec.file), sess_options=options, providers=self.providers
                )
                for name, spec in manifest.graphs.items()
            }
        except Exception as exc:  # onnxruntime raises its own Fail/InvalidGraph/RuntimeError
            raise BackendError(f"ONNX Runtime cannot load the graphs in {folder}: {exc}") from exc
        # each file must be the graph of its role (names and dims as the graph itself says)
        check_graph_signatures(manifest, {
            name: ({node.name: tuple(node.shape) for node in session.get_inputs()},
                   {node.name: tuple(node.shape) for node in session.get_outputs()})
            for name, session in self._sessions.items()
        })

    @property
    def active_providers(self) -> tuple[str, ...]:
        """Execution providers the tracking decoder actually runs on, in priority order."""
        return tuple(self._sessions["decoder_track"].get_providers())

    def _run(self, graph: str, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        try:
            outputs: list[np.ndarray] = self._sessions[graph].run(self._outputs[graph], feeds)
        except Exception as exc:  # onnxruntime's exceptions are not part of our API
            raise BackendError(f"ONNX Runtime failed in graph {graph!r}: {exc}") from exc
        return dict(zip(self._outputs[graph], outputs, strict=True))

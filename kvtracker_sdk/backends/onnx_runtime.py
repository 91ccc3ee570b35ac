"""ONNX Runtime sessions of an export folder, chained into mapping and tracking passes.

``OnnxRunner`` speaks numpy: float32 images in [0, 1], K/V arrays, per-frame outputs in the
SDK's conventions. It knows nothing of ``KVCache`` or uint8 frames (that is ``OnnxBackend``'s
job) so that the exporter can run it on its check inputs too. It serves every family: the
decoders' outputs other than K/V are the heads' inputs, fed to the head graphs by name, and the
family's record (``models.registry.family_named(manifest.family)``) picks the head graphs and
converts their outputs.

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

from kvtracker_sdk.backends.onnx_manifest import (
    OnnxManifest,
    past_key_name,
    past_value_name,
    present_key_name,
    present_value_name,
)
from kvtracker_sdk.errors import BackendError, ConfigError, MissingDependencyError
from kvtracker_sdk.models.family import FrameOutputs
from kvtracker_sdk.models.registry import family_named
from kvtracker_sdk.types import HeadSet

__all__ = ["OnnxRunner", "import_onnxruntime", "providers_for", "session_options"]

def import_onnxruntime() -> Any:
    """The ``onnxruntime`` module, or ``MissingDependencyError`` naming the ``[onnx]`` extra."""
    try:
        return importlib.import_module("onnxruntime")
    except ImportError as exc:
        raise MissingDependencyError(
            f"the ONNX backend needs onnxruntime: pip install 'kvtracker-sdk[onnx]' ({exc})"
        ) from exc


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


class OnnxRunner:
    """One ONNX Runtime session per graph of an export; mapping and tracking passes in numpy."""

    def __init__(
        self,
        folder: str | Path,
        manifest: OnnxManifest,
        *,
        providers: Sequence[Any] | None = None,
        threads: int | None = None,
    ) -> None:
        ort = import_onnxruntime()
        folder = Path(folder)
        self.manifest = manifest
        self.providers = providers_for("cpu", providers)
        self._family = family_named(manifest.family)
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
        self._outputs = {
            name: [spec.name for spec in graph.outputs] for name, graph in manifest.graphs.items()
        }
        self._inputs = {
            name: [spec.name for spec in graph.inputs] for name, graph in manifest.graphs.items()
        }
        self.num_layers = manifest.cache_layout.num_layers

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

    def encode(self, images: np.ndarray) -> np.ndarray:
        """float32 [F, 3, H, W] in [0, 1] -> patch tokens [F, h, w, dim]."""
        return self._run("encoder", {"images": images})["patch_tokens"]

    def map(self, images: np.ndarray) -> tuple[FrameOutputs, list[np.ndarray], list[np.ndarray]]:
        """Full attention over keyframes float32 [N, 3, H, W] in [0, 1]: all heads, and per
        cached layer K and V [1, heads, N*T, head_dim]."""
        decoded = self._run("decoder_map", {"patch_tokens": self.encode(images)})
        keys = [decoded.pop(present_key_name(i)) for i in range(self.num_layers)]
        values = [decoded.pop(present_value_name(i)) for i in range(self.num_layers)]
        return self.heads(decoded, HeadSet.ALL, images.shape[-2:]), keys, values

    def track(
        self,
        image: np.ndarray,
        past: Sequence[tuple[np.ndarray, np.ndarray]],
        past_length: int,
        heads: HeadSet,
    ) -> FrameOutputs:
        """One frame float32 [1, 3, H, W] against a cache.

        ``past[i]`` = (K, V) of cached layer ``i``, [1, heads, capacity, head_dim] float32,
        whose first ``past_length`` tokens are the cached ones (the rest is ignored). Arrays
        that are C-contiguous are read in place.
        """
        feeds = {
            "patch_tokens": self.encode(image),
            "past_length": np.asarray(past_length, dtype=np.int64),
        }
        for layer, (key, value) in enumerate(past):
            feeds[past_key_name(layer)] = key
            feeds[past_value_name(layer)] = value
        return self.heads(self._run("decoder_track", feeds), heads, image.shape[-2:])

    def heads(
        self, decoded: dict[str, np.ndarray], heads: HeadSet, image_size: Sequence[int]
    ) -> FrameOutputs:
        """Run the head graphs ``heads`` needs on the decoder's outputs (fed by name), converted
        to the SDK's conventions for images of ``image_size`` (H, W)."""
        outputs: dict[str, np.ndarray] = {}
        for graph in self._family.head_graphs(heads):
            outputs.update(self._run(graph, {name: decoded[name] for name in self._inputs[graph]}))
        height, width = image_size
        return self._family.convert_heads(outputs, heads, (int(height), int(width)))

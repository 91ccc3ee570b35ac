"""Tracking graphs compiled for the exact shapes they are fed (OpenVINO static shapes).

An export's graphs have dynamic dimensions: the frame count, the patch grid and the cache's
length (``onnx_manifest``). OpenVINO's CPU plugin runs a graph reshaped to static shapes markedly
faster than the dynamic one: it plans memory and picks kernels once, and shape-dependent
subgraphs fold away. Reshaping alone gains little; most of the gain comes from ``past_length``
becoming a constant (the cache slice and the attention over it are then static too). Figures:
``benchmarks/README.md#figures-behind-the-code``.

In a tracker those shapes change only when the map does (a keyframe more, a rebuild at another
resolution), so ``StaticGraphs`` compiles a graph per input signature on first use and keeps the
last few (a small LRU per graph): the first frame after the map changes pays one compile
(logged as ``openvino.static_compile`` with its seconds, and kept in ``compile_seconds``).
Integer scalar inputs (``past_length``) are part of the signature and folded into the graph as
constants. The graphs are the ones read from the verified
export (no compiled-blob cache on disk, so nothing skips the manifest's sha256 check).

A graph OpenVINO cannot compile static-shaped runs dynamic from then on (``infer`` returns None;
logged once as ``openvino.static_unsupported``). Pi3's encoder would be one in OpenVINO 2026.4:
the constant folding of its ``bicubic_pillow`` pos-embed resize (``openvino_graph``) fails ("For
Pillow based modes exactly two (HW) axes need to be provided"), so the runner leaves it out
(``folds_pillow_resize``) instead of paying a failed compile; Pi3's decoder is static.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from typing import Any

import numpy as np

from kvtracker_sdk.log import get_logger

__all__ = ["StaticGraphs", "signature", "specialise"]

_log = get_logger(__name__)

# (input name, shape, value of an integer scalar or None) per input, sorted by name
Signature = tuple[tuple[str, tuple[int, ...], int | None], ...]


def signature(feeds: dict[str, np.ndarray]) -> Signature:
    """What a static compile depends on: every input's shape, and integer scalars' values."""
    return tuple(
        (name, tuple(array.shape), int(array) if _is_int_scalar(array) else None)
        for name, array in sorted(feeds.items())
    )


def _is_int_scalar(array: np.ndarray) -> bool:
    return array.ndim == 0 and np.issubdtype(array.dtype, np.integer)


def specialise(ov: Any, model: Any, feeds: dict[str, np.ndarray]) -> Any:
    """A copy of ``model`` (an ``openvino.Model``) reshaped to ``feeds``' shapes, with integer
    scalar inputs replaced by their values as constants (no longer inputs)."""
    model = model.clone()
    constants = {name: array for name, array in feeds.items() if _is_int_scalar(array)}
    model.reshape(
        {name: list(array.shape) for name, array in feeds.items() if name not in constants}
    )
    for parameter in list(model.get_parameters()):
        names = parameter.output(0).get_names()
        name = next((n for n in names if n in constants), None)
        if name is None:
            continue
        value = ov.op.Constant(np.asarray(constants[name], dtype=parameter.get_element_type()
                                          .to_dtype()))  # fmt: skip
        for target in list(parameter.output(0).get_target_inputs()):
            target.replace_source_output(value.output(0))
        model.remove_parameter(parameter)
    model.validate_nodes_and_infer_types()
    return model


class _Compiled:
    """One static compile and its inference requests, one per thread (see ``openvino_runtime``)."""

    def __init__(self, compiled: Any, constants: frozenset[str]) -> None:
        self.compiled, self.constants = compiled, constants
        self._requests = threading.local()

    def request(self) -> Any:
        request = getattr(self._requests, "request", None)
        if request is None:
            request = self._requests.request = self.compiled.create_infer_request()
        return request


class StaticGraphs:
    """Per graph, compiled models specialised to input signatures (LRU of ``per_graph``).

    ``models``: graph name -> ``openvino.Model`` (dynamic, as read); ``compile``: (graph name,
    model) -> compiled model (the runner's device and that graph's properties). Thread-safe: compiles run one at a
    time, each thread has its own inference request per compiled model.
    """

    def __init__(self, ov: Any, models: dict[str, Any], compile: Any, per_graph: int = 2) -> None:
        if per_graph < 1:
            raise ValueError(f"per_graph must be >= 1, got {per_graph}")
        self._ov, self._models, self._compile, self.per_graph = ov, models, compile, per_graph
        self.graphs = frozenset(models)
        self._cache: dict[str, OrderedDict[Signature, _Compiled]] = {
            n: OrderedDict() for n in models
        }
        self._lock = threading.Lock()
        self.unsupported: set[str] = set()  # graphs whose static compile failed: run dynamic
        self.compile_seconds: list[tuple[str, float]] = []  # (graph, s), in compile order

    def infer(self, graph: str, feeds: dict[str, np.ndarray]) -> Any:
        """Run ``graph`` on ``feeds`` through its compile for their signature; the request's
        results (valid until this thread's next call on the same compile), or None when the
        graph does not compile static-shaped (the caller runs the dynamic one)."""
        entry = self._entry(graph, feeds) if graph in self._models else None
        if entry is None:
            return None
        inputs = {name: array for name, array in feeds.items() if name not in entry.constants}
        return entry.request().infer(inputs, share_inputs=True, share_outputs=False)

    def _entry(self, graph: str, feeds: dict[str, np.ndarray]) -> _Compiled | None:
        key = signature(feeds)
        with self._lock:
            if graph in self.unsupported:
                return None
            cached = self._cache[graph]
            if key in cached:
                cached.move_to_end(key)
                return cached[key]
            start = time.perf_counter()
            try:
                model = specialise(self._ov, self._models[graph], feeds)
                compiled = self._compile(graph, model)
            except Exception as exc:  # OpenVINO's own exceptions: this graph stays dynamic
                self.unsupported.add(graph)
                _log.warning("openvino.static_unsupported", graph=graph, error=str(exc)[:300])
                return None
            seconds = time.perf_counter() - start
            constants = frozenset(n for n, a in feeds.items() if _is_int_scalar(a))
            cached[key] = _Compiled(compiled, constants)
            if len(cached) > self.per_graph:
                cached.popitem(last=False)  # requests in use keep their compile alive
            self.compile_seconds.append((graph, seconds))
            _log.info("openvino.static_compile", graph=graph, seconds=round(seconds, 3),
                      shapes={name: shape for name, shape, _ in key})  # fmt: skip
            return cached[key]

"""OpenVINO compiled models of an export folder, chained into mapping and tracking passes.

``OpenVinoRunner`` is the ``GraphRunner`` (``graph_runner``: the passes, in numpy) whose graphs
OpenVINO reads from the export's ``.onnx`` files (its ONNX frontend; the weights stay in the
shared ``weights.bin``; ``openvino_graph`` fixes the one node it reads differently) and
compiles for a device.

Choices, and why:
- ``INFERENCE_PRECISION_HINT``: "float32" computes the export's function within float rounding
  (the default: it is what the golden tolerances hold for); "bfloat16" lets the CPU plugin run
  matrix products in bf16 where the CPU has them (AVX512-BF16, AMX), accumulating in fp32.
  Inputs and outputs stay float32 either way, so the cache does too: a bf16 OpenVINO backend
  shares caches and maps with every float32 backend of the same weights. The precision the
  plugin actually chose is read back from the compiled model and reported (a CPU without bf16
  computes in f32; OpenVINO's CPU plugin computes an f16 hint in bf16). The hint is the
  plugin's whole-graph switch: every node of a bf16 graph runs bf16, the residual stream too,
  which PyTorch's bf16 keeps in fp32 (``models/layers/precision.py``); so a bf16 OpenVINO pose
  deviates from fp32 more than PyTorch's. "mixed" sets it per graph instead (``graph_precisions``):
  bf16 for the image encoder and the dense heads, fp32 for the decoders, which read and make the
  map, and for the camera head, whose output is the pose; its poses deviate about as PyTorch
  bf16's. The tuner measures all of them (``autotune``).
- ``PERFORMANCE_HINT=LATENCY``: one stream, one request at a time (a tracker runs one frame at a
  time); ``INFERENCE_NUM_THREADS`` = ``threads`` (None: the plugin's choice, one per physical
  core), read back and reported.
- Inputs are shared, not copied (``share_inputs=True``): the cache's float32 buffers are
  C-contiguous and read in place, whatever their scratch capacity. Outputs are copied (the next
  inference would overwrite them).
- ``static_shapes``: tracking passes run on graphs compiled for their exact input shapes,
  ``past_length`` folded in (``openvino_static``: faster, at one compile per new map shape,
  logged; figures: ``benchmarks/README.md#figures-behind-the-code``);
  by default every tracking graph in float32 and all but the tracking decoder with a bf16/f16
  hint (``static_graphs``). Mapping passes, whose keyframe count changes every rebuild, run on the
  dynamic graphs.
- One inference request per graph per thread: a tracker maps (rebuilds) on a worker thread while
  it tracks on another, and both passes run the encoder and the heads; an OpenVINO request must
  not run twice at once, a compiled model may serve several requests.

OpenVINO is imported (telemetry off) and its one ``Core`` kept by ``openvino_core``.
"""

from __future__ import annotations

import threading
from collections.abc import Collection, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kvtracker_sdk.backends.graph_runner import GraphRunner
from kvtracker_sdk.backends.onnx_claims import GraphSignature, check_graph_signatures
from kvtracker_sdk.backends.onnx_manifest import OnnxManifest
from kvtracker_sdk.backends.openvino_core import import_openvino, shared_core
from kvtracker_sdk.backends.openvino_graph import folds_pillow_resize, read_graph
from kvtracker_sdk.backends.openvino_static import StaticGraphs
from kvtracker_sdk.errors import BackendError, ConfigError, MissingDependencyError
from kvtracker_sdk.models.family import FrameOutputs
from kvtracker_sdk.types import HeadSet

__all__ = [
    "PRECISIONS",
    "OpenVinoRunner",
    "compile_config",
    "openvino_device",
    "static_graphs",
]

# SDK dtype name -> OpenVINO's inference precision hint
PRECISIONS = {"float32": "f32", "bfloat16": "bf16", "float16": "f16"}
MIXED = "mixed"  # per graph (graph_precisions): bf16 where the pose does not pass through
# "mixed": the graphs kept fp32: the decoders (their K/V are the map, and every pose is read
# through them) and the camera head (its outputs are the pose itself)
MIXED_FP32_GRAPHS = frozenset({"decoder_map", "decoder_track", "head_camera"})
_DEVICES = {"cpu": "CPU", "gpu": "GPU", "npu": "NPU"}


def openvino_device(device: str, available: list[str]) -> str:
    """SDK device name ("cpu", "gpu[:N]", "npu") -> OpenVINO's ("CPU", "GPU.N", "NPU").

    ``ConfigError`` for an unknown name; ``MissingDependencyError`` when OpenVINO sees no such
    device here (``available``: the Core's ``available_devices``; a GPU or NPU needs its driver).
    """
    kind, _, index = device.lower().partition(":")
    if kind not in _DEVICES or (index and not index.isdigit()):
        raise ConfigError(
            f"unknown OpenVINO device {device!r}; expected one of {sorted(_DEVICES)} (gpu:N too)"
        )
    name = _DEVICES[kind] + (f".{index}" if index else "")
    seen = set(available) | {d.split(".")[0] for d in available}  # "GPU" when "GPU.0" is there
    if name not in seen:
        raise MissingDependencyError(
            f"OpenVINO sees no {name} device here (available: {available}); install its driver"
        )
    return name


def graph_precisions(precision: str, graphs: Collection[str]) -> dict[str, str]:
    """Each graph's precision (a key of ``PRECISIONS``) under the backend's ``precision``: the
    same for all, or for ``MIXED`` float32 for ``MIXED_FP32_GRAPHS`` and bfloat16 for the rest.
    ``ConfigError`` for an unknown precision."""
    if precision == MIXED:
        return {g: "float32" if g in MIXED_FP32_GRAPHS else "bfloat16" for g in graphs}
    if precision not in PRECISIONS:
        known = sorted([*PRECISIONS, MIXED])
        raise ConfigError(f"unknown precision {precision!r}; expected one of {known}")
    return dict.fromkeys(graphs, precision)


def compile_config(device: str, precision: str, threads: int | None) -> dict[str, Any]:
    """Compile properties for one tracking loop on ``device`` (see the module docstring);
    ``precision``: a key of ``PRECISIONS`` (one graph's)."""
    if precision not in PRECISIONS:
        raise ConfigError(f"unknown precision {precision!r}; expected one of {sorted(PRECISIONS)}")
    if threads is not None and threads < 1:
        raise ConfigError(f"threads must be >= 1, got {threads}")
    config: dict[str, Any] = {
        "INFERENCE_PRECISION_HINT": PRECISIONS[precision],
        "PERFORMANCE_HINT": "LATENCY",
    }
    if device == "CPU" and threads is not None:
        config["INFERENCE_NUM_THREADS"] = threads
    return config


def static_graphs(
    static_shapes: bool | Collection[str] | None, manifest: OnnxManifest, precision: str
) -> set[str]:
    """The graphs tracking runs static-shaped: True = every graph but ``decoder_map`` (mapping
    stays dynamic), False = none, the names given (``ConfigError`` for another name), or None
    (default) = every one in float32; with a bf16/f16 hint every one but the tracking decoder:
    the static decoder computes bf16 differently (more of it fused in bf16), and its poses
    deviated more from fp32 than the dynamic decoder's (figures:
    ``benchmarks/README.md#figures-behind-the-code``). The heads are static in bf16 as the
    encoder is: the depth head has no part in the pose, and with the camera head static the
    tuner's pose deviations stayed the same (``benchmarks/results/auto_choice.md``). ``MIXED``
    as float32: every one (its decoder is fp32)."""
    tracking = {name for name in manifest.graphs if name != "decoder_map"}
    if static_shapes is None:
        return tracking if precision in ("float32", MIXED) else tracking - {"decoder_track"}
    if isinstance(static_shapes, bool):
        return tracking if static_shapes else set()
    unknown = sorted(set(static_shapes) - tracking)
    if unknown:
        raise ConfigError(f"static_shapes names {unknown}; tracking graphs: {sorted(tracking)}")
    return set(static_shapes)


def _signature(model: Any, known: set[str]) -> GraphSignature:
    """An ``openvino.Model``'s (inputs, outputs): name -> dims (None where dynamic). A port may
    carry several names; the one in ``known`` (the manifest's) is used if it has one."""

    def dims(port: Any) -> tuple[int | None, ...]:
        return tuple(d.get_length() if d.is_static else None for d in port.get_partial_shape())

    def name(port: Any) -> str:
        return next(iter(sorted(set(port.get_names()) & known)), port.get_any_name())

    return ({name(port): dims(port) for port in model.inputs},
            {name(port): dims(port) for port in model.outputs})


class OpenVinoRunner(GraphRunner):
    """One OpenVINO compiled model per graph of an export; mapping and tracking passes in numpy.

    ``device``: "cpu" (default), "gpu[:N]", "npu"; ``precision``: a key of ``PRECISIONS`` or
    ``MIXED`` (``graph_precisions``);
    ``threads``: CPU inference threads (None: one per physical core); ``static_shapes``: track
    on graphs compiled per input shape (``openvino_static``; ``static_graphs``: None = by
    precision, True, False, or graph names).
    """

    def __init__(
        self,
        folder: str | Path,
        manifest: OnnxManifest,
        *,
        device: str = "cpu",
        precision: str = "float32",
        threads: int | None = None,
        static_shapes: bool | Collection[str] | None = None,
    ) -> None:
        super().__init__(manifest)
        ov = import_openvino()
        folder = Path(folder)
        core = shared_core()
        self.device = openvino_device(device, list(core.available_devices))
        precisions = graph_precisions(precision, manifest.graphs)
        configs = {name: compile_config(self.device, graph_precision, threads)
                   for name, graph_precision in precisions.items()}  # fmt: skip
        static = static_graphs(static_shapes, manifest, precision)
        try:
            models = {
                name: read_graph(core, folder / spec.file) for name, spec in manifest.graphs.items()
            }
            known = {t.name for g in manifest.graphs.values() for t in (*g.inputs, *g.outputs)}
            signatures = {name: _signature(model, known) for name, model in models.items()}
        except Exception as exc:  # OpenVINO raises RuntimeError/its own for unreadable graphs
            raise BackendError(f"OpenVINO cannot read the graphs in {folder}: {exc}") from exc
        # each file must be the graph of its role, checked before anything is compiled
        check_graph_signatures(manifest, signatures)
        try:
            static -= {name for name in static if folds_pillow_resize(models[name])}
            # static shapes: the dynamic tracking decoder is never run (a copy of its weights less)
            self._compiled = {
                name: core.compile_model(model, self.device, configs[name])
                for name, model in models.items()
                if name not in static or name != "decoder_track"
            }
        except Exception as exc:  # OpenVINO raises RuntimeError/its own for unreadable graphs
            raise BackendError(f"OpenVINO cannot compile the graphs in {folder}: {exc}") from exc
        for name, model in models.items():
            self._check_names(name, model)
        chosen = {name: str(compiled.get_property("INFERENCE_PRECISION_HINT").get_type_name())
                  for name, compiled in self._compiled.items()}  # fmt: skip
        # what the plugin chose (a CPU without bf16 computes f32): one name, or MIXED's two
        self.precision = chosen["encoder"]
        if precision == MIXED:
            self.precision = f"{MIXED}({chosen['encoder']}/{chosen['decoder_map']})"
        track = self._compiled["encoder"]
        cpu = self.device == "CPU"
        self.threads = int(track.get_property("INFERENCE_NUM_THREADS")) if cpu else 0
        self._requests = threading.local()  # graph name -> this thread's InferRequest
        self._models, self._compile_lock = models, threading.Lock()
        self._compile = lambda graph, model: core.compile_model(model, self.device, configs[graph])
        self._tracking = threading.local()  # .active: this thread is in a tracking pass
        self.static: StaticGraphs | None = None
        if static:
            self.static = StaticGraphs(ov, {name: models[name] for name in static}, self._compile)

    def _check_names(self, graph: str, compiled: Any) -> None:
        """The graph (an ``openvino.Model`` as read) takes and returns the tensors its manifest
        names."""
        inputs = {name for port in compiled.inputs for name in port.get_names()}
        outputs = {name for port in compiled.outputs for name in port.get_names()}
        missing = sorted(set(self._inputs[graph]) - inputs)
        missing += sorted(set(self._outputs[graph]) - outputs)
        if missing:
            raise BackendError(f"OpenVINO's {graph!r} graph lacks the manifest's tensors {missing}")

    @property
    def accelerations(self) -> tuple[str, ...]:
        """What runs the graphs: device, precision chosen by the plugin, CPU threads."""
        names: tuple[str, ...] = (f"openvino:{self.device}", f"precision:{self.precision}")
        names += (f"threads:{self.threads}",) if self.device == "CPU" else ()
        if self.static is None:
            return names
        static = sorted(self.static.graphs)
        everything = len(static) == len(self._inputs) - 1  # all but decoder_map
        return names + ("static-shapes" if everything else f"static:{','.join(static)}",)

    def track(
        self,
        image: np.ndarray,
        past: Sequence[tuple[np.ndarray, np.ndarray]],
        past_length: int,
        heads: HeadSet,
    ) -> FrameOutputs:
        """``GraphRunner.track``, its graphs run static-shaped when ``static_shapes`` is on."""
        self._tracking.active = True
        try:
            return super().track(image, past, past_length, heads)
        finally:
            self._tracking.active = False

    def _request(self, graph: str) -> Any:
        requests: dict[str, Any] = self._requests.__dict__
        if graph not in requests:
            with self._compile_lock:  # the dynamic tracking decoder: compiled when first needed
                if graph not in self._compiled:
                    self._compiled[graph] = self._compile(graph, self._models[graph])
            requests[graph] = self._compiled[graph].create_infer_request()
        return requests[graph]

    def _run(self, graph: str, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        try:
            results = None
            if self.static is not None and getattr(self._tracking, "active", False):
                results = self.static.infer(graph, feeds)  # None: this graph runs dynamic
            if results is None:
                results = self._request(graph).infer(feeds, share_inputs=True, share_outputs=False)
            return {name: np.asarray(results[name]) for name in self._outputs[graph]}
        except BackendError:
            raise
        except Exception as exc:  # OpenVINO's exceptions are not part of our API
            raise BackendError(f"OpenVINO failed in graph {graph!r}: {exc}") from exc

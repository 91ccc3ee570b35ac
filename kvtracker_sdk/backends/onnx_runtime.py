"""ONNX Runtime sessions of an export folder, chained into Pi3's mapping and tracking passes.

``Pi3OnnxRunner`` speaks numpy: float32 images in [0, 1], K/V arrays, raw head outputs. It
knows nothing of ``KVCache`` or uint8 frames (that is ``OnnxBackend``'s job) so that the
exporter can run it on its check inputs too.

Speed choices (``session_options``): full graph optimisation (``ORT_ENABLE_ALL``: fusions of
LayerNorm, GELU, MatMul+Add...), the CPU memory arena and memory patterns (buffers are reused
from one step to the next), sequential execution with ``threads`` intra-op threads (one
transformer block at a time: there is no parallelism between nodes worth a second pool).
Inputs are passed as numpy arrays, which ONNX Runtime reads in place when they are C-contiguous
(a 1.2 GB cache buffer costs microseconds to bind), so no I/O binding is needed on CPU.

Only the camera head's last step runs outside the graphs: ``camera_poses`` normalises the rows
of the raw 3x3 and projects it onto SO(3) with an SVD in float64 numpy — the function of the
PyTorch head's ``rotation_from_matrix9`` (equal to 1e-12 in float64; the PyTorch backend runs it
in float32, whose rounding is ~1e-6).
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from kvtracker_sdk.backends.onnx_manifest import OnnxManifest, past_key_name, past_value_name
from kvtracker_sdk.errors import BackendError, ConfigError, MissingDependencyError
from kvtracker_sdk.geometry.se3 import project_to_rotation
from kvtracker_sdk.types import HeadSet

__all__ = [
    "HeadOutputs",
    "Pi3OnnxRunner",
    "camera_poses",
    "import_onnxruntime",
    "providers_for",
    "session_options",
]

_HEAD_GRAPHS = {
    HeadSet.CAMERA: ("head_camera",),
    HeadSet.CONFIDENCE: ("head_camera", "head_conf"),
    HeadSet.ALL: ("head_camera", "head_conf", "head_points"),
}


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
    options.log_severity_level = 3  # errors only: the library prints nothing by default
    return options


def camera_poses(rotation_raw: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Camera-to-world poses [F, 4, 4] float64 from the camera head's raw outputs.

    ``rotation_raw`` [F, 9] is a row-major 3x3 per frame: its rows are normalised (as
    ``F.normalize``, eps 1e-12), then it is replaced by the nearest rotation with det = +1
    (SVD). ``translation`` [F, 3].
    """
    matrices = np.asarray(rotation_raw, dtype=np.float64).reshape(-1, 3, 3)
    norms = np.linalg.norm(matrices, axis=-1, keepdims=True)
    matrices = matrices / np.maximum(norms, 1e-12)
    poses = np.tile(np.eye(4), (matrices.shape[0], 1, 1))
    for frame, matrix in enumerate(matrices):
        poses[frame, :3, :3] = project_to_rotation(matrix)
    poses[:, :3, 3] = np.asarray(translation, dtype=np.float64).reshape(-1, 3)
    return poses


@dataclass(frozen=True)
class HeadOutputs:
    """Per-frame outputs of the head graphs (F frames); unrequested heads are None."""

    poses: np.ndarray  # [F, 4, 4] float64 camera-to-world, OpenCV axes
    conf_logits: np.ndarray | None = None  # [F, H, W] float32 (sigmoid -> confidence)
    local_points: np.ndarray | None = None  # [F, H, W, 3] float32, camera frame


class Pi3OnnxRunner:
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
        self.num_layers = manifest.cache_layout.num_layers

    @property
    def active_providers(self) -> tuple[str, ...]:
        """Execution providers the tracking decoder actually runs on, in priority order."""
        return tuple(self._sessions["decoder_track"].get_providers())

    def _run(self, graph: str, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        try:
            outputs: list[np.ndarray] = self._sessions[graph].run(self._outputs[graph], feeds)
        except Exception as exc:  # onnxruntime's exceptions are not part of our API
            raise BackendError(f"ONNX Runtime failed in graph {graph!r}: {exc}") from exc
        return outputs

    def encode(self, images: np.ndarray) -> np.ndarray:
        """float32 [F, 3, H, W] in [0, 1] -> patch tokens [F, h, w, dim]."""
        return self._run("encoder", {"images": images})[0]

    def map(self, images: np.ndarray) -> tuple[HeadOutputs, list[np.ndarray], list[np.ndarray]]:
        """Full attention over keyframes float32 [N, 3, H, W] in [0, 1]: all heads, and per
        cached layer K and V [1, heads, N*T, head_dim]."""
        patch_tokens = self.encode(images)
        hidden_registers, hidden_patches, *kv = self._run(
            "decoder_map", {"patch_tokens": patch_tokens}
        )
        outputs = self.heads(hidden_registers, hidden_patches, HeadSet.ALL)
        return outputs, kv[0::2], kv[1::2]

    def track(
        self,
        image: np.ndarray,
        past: Sequence[tuple[np.ndarray, np.ndarray]],
        past_length: int,
        heads: HeadSet,
    ) -> HeadOutputs:
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
        hidden_registers, hidden_patches = self._run("decoder_track", feeds)
        return self.heads(hidden_registers, hidden_patches, heads)

    def heads(
        self, hidden_registers: np.ndarray, hidden_patches: np.ndarray, heads: HeadSet
    ) -> HeadOutputs:
        """Run the head graphs ``heads`` needs on the decoder's hidden state."""
        feeds = {"hidden_registers": hidden_registers, "hidden_patches": hidden_patches}
        outputs = {name: self._run(name, feeds) for name in _HEAD_GRAPHS[heads]}
        rotation_raw, translation = outputs["head_camera"]
        return HeadOutputs(
            poses=camera_poses(rotation_raw, translation),
            conf_logits=outputs["head_conf"][0] if "head_conf" in outputs else None,
            local_points=outputs["head_points"][0] if "head_points" in outputs else None,
        )

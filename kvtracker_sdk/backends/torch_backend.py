"""``TorchBackend``: the ``Backend`` contract served by a PyTorch model of either family.

    backend = TorchBackend.from_pretrained("da3-small", dtype=torch.bfloat16)   # or "pi3", a file
    mapped = backend.map(keyframes)            # uint8 [N, H, W, 3] at model resolution
    result = backend.track(frame, mapped.cache, heads=HeadSet.CAMERA)

Families: ``pi3`` (π³) and ``da3`` (Depth Anything 3; ``da3-small``, ``da3-base``, ...).
``from_pretrained`` takes a model name (``models.registry.MODEL_NAMES``), a ``.safetensors``
file, a folder or a hub repo id, and picks the family from the checkpoint's tensor names;
``info.family`` / ``info.model`` report it, and caches never cross families (the fingerprint
hashes the family). The passes and the conversion of each family's outputs to the SDK's
conventions are the family record's (``models/<family>/family.py``, looked up in
``models.registry``): ``T_world_cam`` camera-to-world float64, confidence in [0, 1] (DA3:
``1 - 1/depth_conf``), local points in the camera frame (DA3: unprojected depth).

Images arrive at the model resolution (``kvtracker_sdk/preprocess``): uint8 RGB, H and W multiples
of 14. ``map`` runs the full model on the keyframes and returns their poses, confidence and local
points in the pass's own raw frame, plus the ``KVCache`` (K/V of the global layers, in the
backend's dtype). ``track`` runs one frame (``track_batch``: several independent frames in one
pass) against a cache while holding ``cache.lock``; the cache's content is only read.

The backend owns the model it is given: it casts it to ``dtype`` (final heads stay fp32) and moves
it to ``device``; with ``compile`` its ``forward_track`` is replaced by a compiled one
(``backends/torch_compile.py``). ``cuda_graph`` (``True`` or ``GraphOptions(max_keyframes=...)``)
replays the tracking step from CUDA graphs over static cache buffers
(``backends/cuda_graph_step.py``; eager off CUDA). An fp32 backend on CUDA turns cuDNN's TF32 off,
process-wide (fp32 convolutions in TF32 moved DA3's depth off the golden vectors). ``threads``
sets torch's intra-op threads, process-wide (None:
chosen from the usable cores and the load, ``kvtracker_sdk/threads.py``); ``backend.threads``
reports the choice. ``attention="products"`` computes the tracking step's attention over the cache
as two bf16 products instead of SDPA (``models/layers/cached_attention.py``). The weights
fingerprint is taken before the cast, so fp32 and bf16 backends of the same weights report the
same ``info.fingerprint`` (their caches still differ by ``dtype``).
"""

from __future__ import annotations

import os
import time
from typing import Any, cast

import numpy as np
import torch
from torch import nn

from kvtracker_sdk.backends.base import BackendInfo, MapResult, TrackResult
from kvtracker_sdk.backends.cuda_graph_step import GraphOptions, GraphReport, GraphTracking
from kvtracker_sdk.backends.frame_checks import check_cache, check_frames, check_masks
from kvtracker_sdk.backends.torch_compile import CompiledTracking, CompileOptions, CompileReport
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.errors import (
    BackendError,
    ConfigError,
    ImageShapeError,
    StateError,
)
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.models.checkpoint_utils import weights_fingerprint as hash_weights
from kvtracker_sdk.models.family import FrameOutputs, Network
from kvtracker_sdk.models.layers.cached_attention import CACHED_KERNELS, use_cached_kernel
from kvtracker_sdk.models.registry import family_of, load_model
from kvtracker_sdk.threads import ThreadSettings
from kvtracker_sdk.types import HeadSet

__all__ = ["TorchBackend"]

_log = get_logger(__name__)

_DTYPES = {
    "float32": torch.float32,
    "fp32": torch.float32,
    "bfloat16": torch.bfloat16,
    "bf16": torch.bfloat16,
}


def _parse_dtype(dtype: torch.dtype | str) -> torch.dtype:
    resolved = _DTYPES.get(dtype) if isinstance(dtype, str) else dtype
    if resolved not in (torch.float32, torch.bfloat16):
        raise ConfigError(f"TorchBackend dtype must be float32 or bfloat16, got {dtype!r}")
    return resolved


def _available_device(device: torch.device | str) -> torch.device:
    """``device`` parsed, or a typed error: ConfigError for a name torch does not know,
    BackendError for a device this machine lacks (torch itself would fail an assertion)."""
    try:
        resolved = torch.device(device)
    except (RuntimeError, TypeError, ValueError) as exc:
        raise ConfigError(f"unknown device {device!r}: {exc}") from exc
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise BackendError(
            f"device {device!r}: CUDA is not available (this torch build has no CUDA support or "
            "no GPU is visible); use device 'cpu'"
        )
    if resolved.type == "mps" and not torch.backends.mps.is_available():
        raise BackendError(f"device {device!r}: Apple MPS is not available; use device 'cpu'")
    return resolved


def _compile_options(compile: bool | CompileOptions) -> CompileOptions | None:
    if isinstance(compile, CompileOptions):
        return compile
    if isinstance(compile, bool):
        return CompileOptions() if compile else None
    raise ConfigError(f"compile must be a bool or CompileOptions, got {compile!r}")


def _graph_options(cuda_graph: bool | GraphOptions) -> GraphOptions | None:
    if isinstance(cuda_graph, GraphOptions):
        return cuda_graph
    if isinstance(cuda_graph, bool):
        return GraphOptions() if cuda_graph else None
    raise ConfigError(f"cuda_graph must be a bool or GraphOptions, got {cuda_graph!r}")


def _accelerations(device: torch.device) -> tuple[str, ...]:
    """Fast paths in use, detected once: fused SDPA kernels and the CPU vector ISA."""
    if device.type == "cuda":
        flags = {
            "cuda-flash-sdp": torch.backends.cuda.flash_sdp_enabled(),
            "cuda-mem-efficient-sdp": torch.backends.cuda.mem_efficient_sdp_enabled(),
        }
        return ("sdpa", *(name for name, enabled in flags.items() if enabled))
    return ("sdpa", f"cpu-{torch.backends.cpu.get_cpu_capability().lower()}")


def _placed(
    model: nn.Module, network: Network, dtype: torch.dtype, target: torch.device
) -> nn.Module:
    """``model`` cast to ``dtype`` (the family's precision rules), moved to ``target``, in eval
    mode; BackendError when it cannot be moved there."""
    try:
        network.set_precision(dtype)
        return model.to(target).eval()
    except (AssertionError, RuntimeError) as exc:  # e.g. a CUDA index that does not exist
        raise BackendError(f"cannot move the model to {target}: {exc}") from exc


def _keep_fp32_convolutions(target: torch.device, dtype: torch.dtype) -> None:
    """Turn cuDNN's TF32 off, process-wide, for an fp32 backend on CUDA.

    PyTorch lets cuDNN run fp32 convolutions in TF32 by default, which moves DA3's depth off the
    golden vectors by more than their tolerance (``docs/gpu.md``): fp32 means fp32.
    """
    if target.type == "cuda" and dtype == torch.float32 and torch.backends.cudnn.allow_tf32:
        torch.backends.cudnn.allow_tf32 = False
        _log.info("cuDNN TF32 turned off for an fp32 backend on CUDA (process-wide)")


class TorchBackend:
    """Pi3 or Depth Anything 3 on PyTorch; implements ``kvtracker_sdk.backends.base.Backend``.

    ``model_name`` defaults to the architecture's name (``"pi3"``, ``"da3-small"``, ... or
    ``"<family>-custom"``; ``models.registry.model_name``).
    """

    def __init__(
        self,
        model: nn.Module,
        *,
        dtype: torch.dtype | str = torch.float32,
        device: torch.device | str = "cpu",
        model_name: str | None = None,
        weights_fingerprint: str | None = None,
        threads: int | None = None,
        compile: bool | CompileOptions = False,
        attention: str = "sdpa",
        cuda_graph: bool | GraphOptions = False,
    ) -> None:
        compute_dtype = _parse_dtype(dtype)
        graph_options = _graph_options(cuda_graph)
        if graph_options is not None and compile is not False:
            raise ConfigError("choose compile or cuda_graph, not both")
        self._threads = ThreadSettings.resolve(threads, torch.get_num_threads())  # before any work
        compile_options = _compile_options(compile)
        if attention not in CACHED_KERNELS:
            raise ConfigError(f"attention must be one of {CACHED_KERNELS}, got {attention!r}")
        family = family_of(model)  # ModelError for other networks, before any cast
        network = cast(Network, model)
        fingerprint = weights_fingerprint or hash_weights(model.state_dict())
        target = _available_device(device)
        self._model: nn.Module | None = _placed(model, network, compute_dtype, target)
        use_cached_kernel(model, attention)
        _keep_fp32_convolutions(target, compute_dtype)
        torch.set_num_threads(self._threads.threads)
        _log.info("torch threads", settings=self._threads.describe())
        self._compiled: CompiledTracking | None = None
        if compile_options is not None:
            # the family's track calls model.forward_track: the instance attribute shadows it
            self._compiled = CompiledTracking(model, compile_options)
            cast(Any, model).forward_track = self._compiled
        self._graphs: GraphTracking | None = None
        if graph_options is not None:
            self._graphs = GraphTracking(model, family.cache_layout(model), graph_options)
            cast(Any, model).forward_track = self._graphs
        self._family = family
        # the resolved device ("cuda" -> "cuda:0"), so that it compares equal to tensors' devices
        self._device = next(model.parameters()).device
        self._info = BackendInfo(
            backend="torch",
            model=model_name or family.model_name(model),
            family=family.name,
            config_hash=network.config.config_hash,
            weights_fingerprint=fingerprint,
            patch_size=network.config.patch_size,
            extra_tokens_per_frame=family.extra_tokens_per_frame(model),
            layout=family.cache_layout(model),
            dtype=str(compute_dtype).removeprefix("torch."),
            device=str(self._device),
            accelerations=_accelerations(self._device)
            + (() if attention == "sdpa" else (f"cached-attention-{attention}",))
            + (() if compile_options is None else (compile_options.describe(),))
            + (() if graph_options is None else (graph_options.describe(),)),
        )

    @classmethod
    def from_pretrained(
        cls,
        weights: str | os.PathLike[str],
        *,
        config: Any | None = None,
        dtype: torch.dtype | str = torch.float32,
        device: torch.device | str = "cpu",
        model_name: str | None = None,
        threads: int | None = None,
        compile: bool | CompileOptions = False,
        attention: str = "sdpa",
        cuda_graph: bool | GraphOptions = False,
    ) -> TorchBackend:
        """Load a model of either family: a name (``"pi3"``, ``"da3-small"``, ``"da3-base"``,
        ...), a ``.safetensors`` file, a folder or a hub repo id; the family comes from the
        checkpoint's tensor names."""
        _available_device(device)  # before the minutes a large checkpoint may take to load
        loaded = load_model(weights, config=config)
        return cls(
            loaded.model,
            dtype=dtype,
            device=device,
            model_name=model_name or loaded.name,
            weights_fingerprint=loaded.fingerprint,
            threads=threads,
            compile=compile,
            attention=attention,
            cuda_graph=cuda_graph,
        )

    # ------------------------------------------------------------------ Backend protocol
    @property
    def info(self) -> BackendInfo:
        return self._info

    @property
    def threads(self) -> ThreadSettings:
        """The intra-op thread count this backend set, how it was chosen, the OpenMP wait policy."""
        return self._threads

    @property
    def compile_report(self) -> CompileReport | None:
        """The compiled tracking step's status and first-call time (None: not compiled)."""
        return None if self._compiled is None else self._compiled.report

    @property
    def graph_report(self) -> GraphReport | None:
        """The CUDA-graph step's captures, replays and eager calls (None: not enabled)."""
        return None if self._graphs is None else self._graphs.report

    def map(self, images: np.ndarray, masks: np.ndarray | None = None) -> MapResult:
        """Full attention over keyframes uint8 [N, H, W, 3]; the cache lists keyframes 0..N-1."""
        model = self._live_model()
        frames = self._to_tensor(images)
        check_masks(masks, images)
        start = time.perf_counter()
        with torch.no_grad():
            mapped = self._family.map(model, frames)
        outputs = mapped.frames
        return MapResult.of_pass(
            outputs.poses,
            outputs.confidence,
            outputs.local_points,
            mapped.keys,
            mapped.values,
            info=self._info,
            image_size=images.shape[1:3],
            map_ms=(time.perf_counter() - start) * 1e3,
            intrinsics=outputs.intrinsics,
        )

    def track(
        self, image: np.ndarray, cache: KVCache, *, heads: HeadSet = HeadSet.CONFIDENCE
    ) -> TrackResult:
        """Track one frame uint8 [H, W, 3] against ``cache`` (pose in the cache's raw frame)."""
        if not isinstance(image, np.ndarray) or image.ndim != 3:
            raise ImageShapeError(
                f"track expects one image [H, W, 3], got {getattr(image, 'shape', type(image))}"
            )
        return self.track_batch(image[None], cache, heads=heads)[0]

    def track_batch(
        self, images: np.ndarray, cache: KVCache, *, heads: HeadSet = HeadSet.CONFIDENCE
    ) -> list[TrackResult]:
        """Track independent frames uint8 [B, H, W, 3] against ``cache`` in one pass."""
        model = self._live_model()
        images = check_frames(images, self._info.patch_size)
        check_cache(cache, self._info, images.shape[1], images.shape[2])
        start = time.perf_counter()
        with cache.lock, torch.no_grad():
            frames = self._upload(images)
            output = self._family.track(model, frames, cache, heads)
        elapsed_ms = (time.perf_counter() - start) * 1e3
        timings = {"track": elapsed_ms / frames.shape[0], "track_batch": elapsed_ms}
        return [self._track_result(output, index, timings) for index in range(frames.shape[0])]

    def close(self) -> None:
        """Drop the model (frees its memory); later calls raise ``StateError``. Idempotent."""
        self._model = None

    # ------------------------------------------------------------------ helpers
    def _live_model(self) -> nn.Module:
        if self._model is None:
            raise StateError("this TorchBackend is closed")
        return self._model

    def _to_tensor(self, images: np.ndarray) -> torch.Tensor:
        """uint8 [N, H, W, 3] -> float [N, 3, H, W] in [0, 1] on the backend's device."""
        return self._upload(check_frames(images, self._info.patch_size))

    def _upload(self, images: np.ndarray) -> torch.Tensor:
        """Checked frames (``check_frames``) -> float [N, 3, H, W] in [0, 1] on the device."""
        # torch wants writable memory: read-only arrays (e.g. a map's stored keyframes) are copied
        writable = images if images.flags.writeable else images.copy()
        # a plain copy: page-locked staging gained nothing measurable against a step on a GPU
        # (benchmarks/gpu_check.py, section upload)
        tensor = torch.from_numpy(np.ascontiguousarray(writable)).to(self._device)
        if images.dtype == np.float32:  # already in [0, 1] (check_frames)
            return tensor.permute(0, 3, 1, 2).contiguous()
        return tensor.permute(0, 3, 1, 2).float().div_(255.0)

    @staticmethod
    def _track_result(output: FrameOutputs, index: int, timings: dict[str, float]) -> TrackResult:
        confidence_map = None if output.confidence is None else output.confidence[index]
        local_points = None if output.local_points is None else output.local_points[index]
        return TrackResult(
            pose=output.poses[index],
            confidence=None if confidence_map is None else float(confidence_map.mean()),
            confidence_map=confidence_map,
            local_points=local_points,
            timings_ms=timings,
            intrinsics=None if output.intrinsics is None else output.intrinsics[index],
        )

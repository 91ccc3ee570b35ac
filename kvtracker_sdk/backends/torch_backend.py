"""``TorchBackend``: the ``Backend`` contract served by a PyTorch model of either family.

    backend = TorchBackend.from_pretrained("da3-small", dtype=torch.bfloat16)   # or "pi3", a file
    mapped = backend.map(keyframes)            # uint8 [N, H, W, 3] at model resolution
    result = backend.track(frame, mapped.cache, heads=HeadSet.CAMERA)

Families: ``pi3`` (π³) and ``da3`` (Depth Anything 3; ``da3-small``, ``da3-base``, ...).
``from_pretrained`` takes a model name (``models.registry.MODEL_NAMES``), a ``.safetensors``
file, a folder or a hub repo id, and picks the family from the checkpoint's tensor names;
``info.family`` / ``info.model`` report it, and caches never cross families (the fingerprint
hashes the family). Each family's outputs are converted to the SDK's conventions by its adapter
(``backends/torch_families.py``): ``T_world_cam`` camera-to-world float64, confidence in [0, 1]
(DA3: ``1 - 1/depth_conf``), local points in the camera frame (DA3: unprojected depth).

Images arrive at the model resolution (``kvtracker_sdk/preprocess``): uint8 RGB, H and W multiples
of 14. ``map`` runs the full model on the keyframes and returns their poses, confidence and local
points in the pass's own raw frame, plus the ``KVCache`` (K/V of the global layers, in the
backend's dtype). ``track`` runs one frame (``track_batch``: several independent frames in one
pass) against a cache while holding ``cache.lock``; the cache's content is only read.

The backend owns the model it is given: it casts it to ``dtype`` (final heads stay fp32) and moves
it to ``device``. The weights fingerprint is taken before the cast, so fp32 and bf16 backends of
the same weights report the same ``info.fingerprint`` (their caches still differ by ``dtype``).
"""

from __future__ import annotations

import os
import time

import numpy as np
import torch

from kvtracker_sdk.backends.base import BackendInfo, MapResult, TrackResult
from kvtracker_sdk.backends.frame_checks import check_cache, check_frames, check_masks
from kvtracker_sdk.backends.torch_families import FrameOutputs, TorchFamily, family_adapter
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.errors import (
    BackendError,
    ConfigError,
    ImageShapeError,
    StateError,
)
from kvtracker_sdk.models.checkpoint_utils import weights_fingerprint as hash_weights
from kvtracker_sdk.models.da3 import DA3Config, DepthAnything3
from kvtracker_sdk.models.pi3 import Pi3, Pi3Config
from kvtracker_sdk.models.registry import load_model
from kvtracker_sdk.models.registry import model_name as architecture_name
from kvtracker_sdk.types import HeadSet

__all__ = ["TorchBackend"]

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


def _accelerations(device: torch.device) -> tuple[str, ...]:
    """Fast paths in use, detected once: fused SDPA kernels and the CPU vector ISA."""
    if device.type == "cuda":
        flags = {
            "cuda-flash-sdp": torch.backends.cuda.flash_sdp_enabled(),
            "cuda-mem-efficient-sdp": torch.backends.cuda.mem_efficient_sdp_enabled(),
        }
        return ("sdpa", *(name for name, enabled in flags.items() if enabled))
    return ("sdpa", f"cpu-{torch.backends.cpu.get_cpu_capability().lower()}")


class TorchBackend:
    """Pi3 or Depth Anything 3 on PyTorch; implements ``kvtracker_sdk.backends.base.Backend``.

    ``model_name`` defaults to the architecture's name (``"pi3"``, ``"da3-small"``, ... or
    ``"<family>-custom"``; ``models.registry.model_name``).
    """

    def __init__(
        self,
        model: Pi3 | DepthAnything3,
        *,
        dtype: torch.dtype | str = torch.float32,
        device: torch.device | str = "cpu",
        model_name: str | None = None,
        weights_fingerprint: str | None = None,
    ) -> None:
        compute_dtype = _parse_dtype(dtype)
        family = family_adapter(model)  # ModelError for other networks, before any cast
        fingerprint = weights_fingerprint or hash_weights(model.state_dict())
        target = _available_device(device)
        try:
            self._model: Pi3 | DepthAnything3 | None = (
                model.set_precision(compute_dtype).to(target).eval()
            )
        except (AssertionError, RuntimeError) as exc:  # e.g. a CUDA index that does not exist
            raise BackendError(f"cannot move the model to {target}: {exc}") from exc
        self._family: TorchFamily | None = family
        # the resolved device ("cuda" -> "cuda:0"), so that it compares equal to tensors' devices
        self._device = next(model.parameters()).device
        self._info = BackendInfo(
            backend="torch",
            model=model_name or architecture_name(model),
            family=family.family,
            config_hash=model.config.config_hash,
            weights_fingerprint=fingerprint,
            patch_size=model.config.patch_size,
            extra_tokens_per_frame=family.extra_tokens_per_frame,
            layout=family.layout,
            dtype=str(compute_dtype).removeprefix("torch."),
            device=str(self._device),
            accelerations=_accelerations(self._device),
        )

    @classmethod
    def from_pretrained(
        cls,
        weights: str | os.PathLike[str],
        *,
        config: Pi3Config | DA3Config | None = None,
        dtype: torch.dtype | str = torch.float32,
        device: torch.device | str = "cpu",
        model_name: str | None = None,
    ) -> TorchBackend:
        """Load a model of either family: a name (``"pi3"``, ``"da3-small"``, ``"da3-base"``,
        ...), a ``.safetensors`` file, a folder or a hub repo id; the family comes from the
        checkpoint's tensor names."""
        _available_device(device)  # before the minutes a large checkpoint may take to load
        loaded = load_model(weights, config=config)
        return cls(
            loaded.model,  # type: ignore[arg-type]
            dtype=dtype,
            device=device,
            model_name=model_name or loaded.name,
            weights_fingerprint=loaded.fingerprint,
        )

    # ------------------------------------------------------------------ Backend protocol
    @property
    def info(self) -> BackendInfo:
        return self._info

    def map(self, images: np.ndarray, masks: np.ndarray | None = None) -> MapResult:
        """Full attention over keyframes uint8 [N, H, W, 3]; the cache lists keyframes 0..N-1."""
        family = self._live_family()
        frames = self._to_tensor(images)
        check_masks(masks, images)
        start = time.perf_counter()
        with torch.no_grad():
            mapped = family.map(frames)
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
        family = self._live_family()
        frames = self._to_tensor(images)
        check_cache(cache, self._info, frames.shape[-2], frames.shape[-1])
        start = time.perf_counter()
        with cache.lock, torch.no_grad():
            output = family.track(frames, cache, heads)
        elapsed_ms = (time.perf_counter() - start) * 1e3
        timings = {"track": elapsed_ms / frames.shape[0], "track_batch": elapsed_ms}
        return [self._track_result(output, index, timings) for index in range(frames.shape[0])]

    def close(self) -> None:
        """Drop the model (frees its memory); later calls raise ``StateError``. Idempotent."""
        self._model = None
        self._family = None

    # ------------------------------------------------------------------ helpers
    def _live_model(self) -> Pi3 | DepthAnything3:
        if self._model is None:
            raise StateError("this TorchBackend is closed")
        return self._model

    def _live_family(self) -> TorchFamily:
        if self._family is None:
            raise StateError("this TorchBackend is closed")
        return self._family

    def _to_tensor(self, images: np.ndarray) -> torch.Tensor:
        """uint8 [N, H, W, 3] -> float [N, 3, H, W] in [0, 1] on the backend's device."""
        images = check_frames(images, self._info.patch_size)
        # torch wants writable memory: read-only arrays (e.g. a map's stored keyframes) are copied
        writable = images if images.flags.writeable else images.copy()
        tensor = torch.from_numpy(np.ascontiguousarray(writable)).to(self._device)
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
        )

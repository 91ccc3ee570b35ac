"""``TorchBackend``: the ``Backend`` contract served by the PyTorch Pi3 model (CPU or GPU, fp32 or bf16).

    backend = TorchBackend.from_pretrained("yyfz233/Pi3", dtype=torch.bfloat16)   # or a local file
    mapped = backend.map(keyframes)            # uint8 [N, H, W, 3] at model resolution
    result = backend.track(frame, mapped.cache, heads=HeadSet.CAMERA)

Images arrive at the model resolution (``backends/preprocess.py``): uint8 RGB, H and W multiples
of 14. ``map`` runs the full model on the keyframes and returns their poses, confidence and local
points in the pass's own raw frame, plus the ``KVCache`` (K/V of the 18 global layers, in the
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
from kvtracker_sdk.cache.kv_cache import CacheLayout, KVCache
from kvtracker_sdk.errors import (
    BackendMismatchError,
    ConfigError,
    ImageDtypeError,
    ImageShapeError,
    MaskError,
    ResolutionChangedError,
    StateError,
)
from kvtracker_sdk.models.pi3 import Pi3, Pi3Config, Pi3Output, load_pi3
from kvtracker_sdk.models.pi3.checkpoint import weights_fingerprint as hash_weights
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
    """Pi3 on PyTorch; implements ``kvtracker_sdk.backends.base.Backend``."""

    def __init__(
        self,
        model: Pi3,
        *,
        dtype: torch.dtype | str = torch.float32,
        device: torch.device | str = "cpu",
        model_name: str = "pi3-custom",
        weights_fingerprint: str | None = None,
    ) -> None:
        compute_dtype = _parse_dtype(dtype)
        fingerprint = weights_fingerprint or hash_weights(model.state_dict())
        self._model: Pi3 | None = model.set_precision(compute_dtype).to(device).eval()
        # the resolved device ("cuda" -> "cuda:0"), so that it compares equal to tensors' devices
        self._device = model.register_token.device
        decoder = model.decoder
        self._layout = CacheLayout(
            decoder.global_block_indices, decoder.num_heads, decoder.head_dim
        )
        self._info = BackendInfo(
            backend="torch",
            model=model_name,
            family="pi3",
            config_hash=model.config.config_hash,
            weights_fingerprint=fingerprint,
            patch_size=model.config.patch_size,
            extra_tokens_per_frame=model.num_register_tokens,
            layout=self._layout,
            dtype=str(compute_dtype).removeprefix("torch."),
            device=str(self._device),
            accelerations=_accelerations(self._device),
        )

    @classmethod
    def from_pretrained(
        cls,
        weights: str | os.PathLike[str],
        *,
        config: Pi3Config | None = None,
        dtype: torch.dtype | str = torch.float32,
        device: torch.device | str = "cpu",
        model_name: str | None = None,
    ) -> TorchBackend:
        """Load a checkpoint (``.safetensors`` file, folder, or hub repo id like ``yyfz233/Pi3``)."""
        loaded = load_pi3(weights, config=config)
        name = model_name or ("pi3" if loaded.model.config == Pi3Config.large() else "pi3-custom")
        return cls(
            loaded.model,
            dtype=dtype,
            device=device,
            model_name=name,
            weights_fingerprint=loaded.fingerprint,
        )

    # ------------------------------------------------------------------ Backend protocol
    @property
    def info(self) -> BackendInfo:
        return self._info

    def map(self, images: np.ndarray, masks: np.ndarray | None = None) -> MapResult:
        """Full attention over keyframes uint8 [N, H, W, 3]; the cache lists keyframes 0..N-1."""
        model = self._live_model()
        frames = self._to_tensor(images)
        if masks is not None and (masks.dtype != np.bool_ or masks.shape != images.shape[:3]):
            raise MaskError(
                f"masks must be bool {images.shape[:3]}, got {masks.dtype} {masks.shape}"
            )
        start = time.perf_counter()
        with torch.no_grad():
            mapped = model.forward_map(frames.unsqueeze(0), heads=HeadSet.ALL)
        cache = KVCache.from_layers(
            mapped.keys,
            mapped.values,
            layout=self._layout,
            tokens_per_frame=mapped.tokens_per_frame,
            keyframe_ids=range(frames.shape[0]),
        )
        output = mapped.output
        assert output.conf is not None and output.local_points is not None  # HeadSet.ALL
        return MapResult(
            poses=output.camera_poses[0].to(torch.float64).cpu().numpy(),
            confidence=torch.sigmoid(output.conf[0, ..., 0]).cpu().numpy(),
            local_points=output.local_points[0].cpu().numpy(),
            cache=cache,
            timings_ms={"map": (time.perf_counter() - start) * 1e3},
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
        frames = self._to_tensor(images)
        self._check_cache(cache, frames.shape[-2], frames.shape[-1])
        start = time.perf_counter()
        with cache.lock, torch.no_grad():
            output = model.forward_track(frames, cache, heads=heads)
        elapsed_ms = (time.perf_counter() - start) * 1e3
        timings = {"track": elapsed_ms / frames.shape[0], "track_batch": elapsed_ms}
        return [self._track_result(output, index, timings) for index in range(frames.shape[0])]

    def close(self) -> None:
        """Drop the model (frees its memory); later calls raise ``StateError``. Idempotent."""
        self._model = None

    # ------------------------------------------------------------------ helpers
    def _live_model(self) -> Pi3:
        if self._model is None:
            raise StateError("this TorchBackend is closed")
        return self._model

    def _to_tensor(self, images: np.ndarray) -> torch.Tensor:
        """uint8 [N, H, W, 3] -> float [N, 3, H, W] in [0, 1] on the backend's device."""
        if not isinstance(images, np.ndarray):
            raise ImageDtypeError(
                f"images must be a numpy uint8 array, got {type(images).__name__}"
            )
        if images.ndim != 4 or images.shape[-1] != 3 or images.shape[0] == 0:
            raise ImageShapeError(
                f"expected images [N, H, W, 3] with N >= 1, got shape {images.shape}"
            )
        if images.dtype != np.uint8:
            raise ImageDtypeError(f"images must be uint8 RGB, got {images.dtype}")
        height, width = images.shape[1:3]
        patch = self._info.patch_size
        if height % patch or width % patch or height < patch or width < patch:
            raise ImageShapeError(
                f"image size {height}x{width} is not a positive multiple of {patch}: resize it with "
                "kvtracker_sdk.backends.preprocess.model_resolution / resize_image first"
            )
        tensor = torch.from_numpy(np.ascontiguousarray(images)).to(self._device)
        return tensor.permute(0, 3, 1, 2).float().div_(255.0)

    def _check_cache(self, cache: KVCache, height: int, width: int) -> None:
        if cache.layout != self._layout:
            raise BackendMismatchError(
                f"cache layout {cache.layout} does not match this model's {self._layout}"
            )
        if cache.dtype != self._live_model().compute_dtype or cache.device != self._device:
            raise BackendMismatchError(
                f"cache is {cache.dtype} on {cache.device}, the backend computes in {self._info.dtype} on "
                f"{self._device}: convert it with cache.to(dtype=..., device=...)"
            )
        expected = self._info.tokens_per_frame(height, width)
        if cache.tokens_per_frame != expected:
            raise ResolutionChangedError(
                f"the cache holds {cache.tokens_per_frame} tokens per keyframe but a {height}x{width} frame "
                f"has {expected}: track at the keyframes' resolution"
            )

    @staticmethod
    def _track_result(output: Pi3Output, index: int, timings: dict[str, float]) -> TrackResult:
        pose = output.camera_poses[index, 0].to(torch.float64).cpu().numpy()
        confidence_map = None
        if output.conf is not None:
            confidence_map = torch.sigmoid(output.conf[index, 0, ..., 0]).cpu().numpy()
        local_points = (
            None if output.local_points is None else output.local_points[index, 0].cpu().numpy()
        )
        return TrackResult(
            pose=pose,
            confidence=None if confidence_map is None else float(confidence_map.mean()),
            confidence_map=confidence_map,
            local_points=local_points,
            timings_ms=timings,
        )

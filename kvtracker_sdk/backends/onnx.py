"""``OnnxBackend``: the ``Backend`` contract served by ONNX Runtime from an exported folder.

    backend = OnnxBackend("pi3-onnx/")                      # kvtracker export-onnx made the folder
    backend = OnnxBackend("da3-small-onnx/", device="cuda") # with onnxruntime-gpu installed
    backend = onnx_backend("model.safetensors")             # kvtracker_sdk.export_onnx: exported once
    mapped = backend.map(keyframes)                         # uint8 [N, H, W, 3] at model resolution
    result = backend.track(frame, mapped.cache, heads=HeadSet.CAMERA)

It serves both families (the manifest names the export's: ``pi3`` or ``da3``) and computes the
same function as ``TorchBackend`` with the same weights: ``info.fingerprint``
and ``info.layout`` are equal (read from the export's manifest), so a tracker swaps between the
two live (``Tracker.set_backend``) and maps saved by one load in the other. The cache is a
float32 ``KVCache`` on the CPU (where ONNX Runtime reads its inputs, whatever the provider):
tracking hands each layer's whole buffer to the graph as a numpy view — no copy — with the
number of cached tokens, and the graph ignores the scratch tokens after them.

onnxruntime is imported when a backend is created (``MissingDependencyError`` names the
``[onnx]`` extra without it). PyTorch is still needed for the ``KVCache`` itself, not to compute.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from kvtracker_sdk.backends.base import BackendInfo, MapResult, TrackResult
from kvtracker_sdk.backends.frame_checks import check_cache, check_frames, check_masks
from kvtracker_sdk.backends.onnx_integrity import verify_files
from kvtracker_sdk.backends.onnx_manifest import MANIFEST_NAME, OnnxManifest, read_manifest
from kvtracker_sdk.backends.onnx_runtime import OnnxRunner, providers_for
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.errors import ImageShapeError, ModelError, StateError
from kvtracker_sdk.models.family import FrameOutputs
from kvtracker_sdk.types import HeadSet

__all__ = ["OnnxBackend"]


class OnnxBackend:
    """Pi3 or Depth Anything 3 on ONNX Runtime; implements ``kvtracker_sdk.backends.base.Backend``.

    ``folder``: an export (``kvtracker export-onnx``); its files must match the sha256 digests
    of its manifest (``ModelError`` otherwise). ``device``: "cpu" (default), "cuda[:N]",
    "coreml" or "directml", where the installed onnxruntime provides it; ``providers`` (names or
    (name, options) pairs) overrides it. ``threads``: intra-op CPU threads (None: one per
    physical core).
    """

    def __init__(
        self,
        folder: str | os.PathLike[str],
        *,
        device: str = "cpu",
        providers: Sequence[Any] | None = None,
        threads: int | None = None,
    ) -> None:
        self.folder = Path(folder)
        self.manifest: OnnxManifest = read_manifest(self.folder)
        verify_files(self.folder, self.manifest.sha256)  # before ONNX Runtime reads a byte
        self._runner: OnnxRunner | None = OnnxRunner(
            self.folder, self.manifest, providers=providers_for(device, providers), threads=threads
        )
        # the cache stays on the CPU whatever the provider: ORT reads host memory
        self._info = self.manifest.backend_info(
            device="cpu", accelerations=self._runner.active_providers
        )

    @classmethod
    def from_pretrained(
        cls,
        source: str | os.PathLike[str],
        *,
        device: str = "cpu",
        providers: Sequence[Any] | None = None,
        threads: int | None = None,
    ) -> OnnxBackend:
        """An export folder (as ``TorchBackend.from_pretrained`` takes a checkpoint).

        A checkpoint is exported by a layer above this one: ``kvtracker_sdk.export_onnx.
        onnx_backend(checkpoint)`` exports it once into a cache folder and serves the export
        (``kvtracker track --backend onnx --weights model.safetensors`` does that).
        """
        folder = Path(source)
        if not (folder / MANIFEST_NAME).is_file():
            raise ModelError(
                f"{source} is not an ONNX export (no {MANIFEST_NAME}); export a checkpoint with "
                "kvtracker_sdk.export_onnx.onnx_backend(weights) or `kvtracker export-onnx`"
            )
        return cls(folder, device=device, providers=providers, threads=threads)

    # ------------------------------------------------------------------ Backend protocol
    @property
    def info(self) -> BackendInfo:
        return self._info

    def map(self, images: np.ndarray, masks: np.ndarray | None = None) -> MapResult:
        """Full attention over keyframes uint8 [N, H, W, 3]; the cache lists keyframes 0..N-1."""
        runner = self._live_runner()
        frames = self._to_input(images)
        check_masks(masks, images)
        start = time.perf_counter()
        outputs, keys, values = runner.map(frames)
        return MapResult.of_pass(
            outputs.poses,
            outputs.confidence,
            outputs.local_points,
            [torch.from_numpy(k) for k in keys],
            [torch.from_numpy(v) for v in values],
            info=self._info,
            image_size=images.shape[1:3],
            map_ms=(time.perf_counter() - start) * 1e3,
            intrinsics=outputs.intrinsics,
        )

    def track(
        self, image: np.ndarray, cache: KVCache, *, heads: HeadSet = HeadSet.CONFIDENCE
    ) -> TrackResult:
        """Track one frame uint8 [H, W, 3] against ``cache`` (pose in the cache's raw frame).

        The cache is only read (under ``cache.lock``); it must be float32 on the CPU
        (``cache.to(dtype=torch.float32, device="cpu")`` converts one made elsewhere).
        """
        runner = self._live_runner()
        if not isinstance(image, np.ndarray) or image.ndim != 3:
            raise ImageShapeError(
                f"track expects one image [H, W, 3], got {getattr(image, 'shape', type(image))}"
            )
        frame = self._to_input(image[None])
        check_cache(cache, self._info, *image.shape[:2])
        start = time.perf_counter()
        with cache.lock:
            past = [
                tuple(np.ascontiguousarray(buffer.numpy()) for buffer in cache.buffers(layer))
                for layer in range(cache.layout.num_layers)
            ]
            outputs = runner.track(frame, past, cache.length, heads)  # type: ignore[arg-type]
        return self._track_result(outputs, {"track": (time.perf_counter() - start) * 1e3})

    def close(self) -> None:
        """Release the sessions (and their memory); later calls raise ``StateError``. Idempotent."""
        self._runner = None

    # ------------------------------------------------------------------ helpers
    def _live_runner(self) -> OnnxRunner:
        if self._runner is None:
            raise StateError("this OnnxBackend is closed")
        return self._runner

    def _to_input(self, images: np.ndarray) -> np.ndarray:
        """uint8 [N, H, W, 3] -> float32 [N, 3, H, W] in [0, 1], C-contiguous."""
        frames = check_frames(images, self._info.patch_size)
        planar = np.ascontiguousarray(frames.transpose(0, 3, 1, 2), dtype=np.float32)
        return planar if frames.dtype == np.float32 else planar / 255.0

    @staticmethod
    def _track_result(outputs: FrameOutputs, timings: dict[str, float]) -> TrackResult:
        confidence_map = None if outputs.confidence is None else outputs.confidence[0]
        return TrackResult(
            pose=outputs.poses[0],
            confidence=None if confidence_map is None else float(confidence_map.mean()),
            confidence_map=confidence_map,
            local_points=None if outputs.local_points is None else outputs.local_points[0],
            timings_ms=timings,
            intrinsics=None if outputs.intrinsics is None else outputs.intrinsics[0],
        )

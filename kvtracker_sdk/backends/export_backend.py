"""``ExportBackend``: the ``Backend`` contract over an export folder's graphs, whatever runs them.

``OnnxBackend`` (ONNX Runtime) and ``OpenVinoBackend`` (OpenVINO) serve the same export folder
(``kvtracker export-onnx``) with the cache as graph inputs; what they share lives here: reading
the manifest and verifying every file against its sha256 before a runtime reads a byte
(``onnx_integrity``), the input checks, uint8 frames -> float32 planar input, the ``KVCache``
handed to the tracking graph as numpy views (no copy), and the results. A subclass builds its
``GraphRunner`` and ``BackendInfo`` and calls ``_serve``.

Both compute the function of ``TorchBackend`` with the same weights: ``info.fingerprint`` and
``info.layout`` are equal (read from the export's manifest), so a tracker swaps between them live
(``Tracker.set_backend``) and maps saved by one load in the others. The cache is a float32
``KVCache`` on the CPU (where both runtimes read their inputs, whatever the device).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import torch

from kvtracker_sdk.backends.base import BackendInfo, MapResult, TrackResult
from kvtracker_sdk.backends.frame_checks import (
    check_cache,
    check_frames,
    check_masks,
    check_uniform_lengths,
)
from kvtracker_sdk.backends.graph_runner import GraphRunner
from kvtracker_sdk.backends.onnx_integrity import verify_files
from kvtracker_sdk.backends.onnx_manifest import MANIFEST_NAME, OnnxManifest, read_manifest
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.errors import ImageShapeError, ModelError, StateError
from kvtracker_sdk.models.family import FrameOutputs
from kvtracker_sdk.types import HeadSet

__all__ = ["ExportBackend", "export_folder"]


def export_folder(source: str | os.PathLike[str]) -> Path:
    """``source`` as an export folder, or ``ModelError`` saying how to make one.

    A checkpoint is exported by a layer above the backends: ``kvtracker_sdk.export_onnx.
    onnx_backend(checkpoint)`` / ``openvino_backend(checkpoint)`` export it once into a cache
    folder and serve the export (``kvtracker track --weights model.safetensors`` does that).
    """
    folder = Path(source)
    if not (folder / MANIFEST_NAME).is_file():
        raise ModelError(
            f"{source} is not an ONNX export (no {MANIFEST_NAME}); export a checkpoint with "
            "kvtracker_sdk.export_onnx.onnx_backend(weights) or `kvtracker export-onnx`"
        )
    return folder


class ExportBackend:
    """An export folder served by a ``GraphRunner``; implements ``backends.base.Backend``.

    The constructor reads and verifies the folder (``ModelError`` when a file does not match the
    manifest's sha256); the subclass then builds its runner and calls ``_serve``.
    """

    def __init__(self, folder: str | os.PathLike[str]) -> None:
        self.folder = Path(folder)
        self.manifest: OnnxManifest = read_manifest(self.folder)
        verify_files(self.folder, self.manifest.sha256)  # before a runtime reads a byte
        self._runner: GraphRunner | None = None
        self._info: BackendInfo | None = None

    def _serve(self, runner: GraphRunner, info: BackendInfo) -> None:
        self._runner, self._info = runner, info

    # ------------------------------------------------------------------ Backend protocol
    @property
    def info(self) -> BackendInfo:
        assert self._info is not None, "a subclass calls _serve in its constructor"
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
            info=self.info,
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
        check_cache(cache, self.info, *image.shape[:2])
        start = time.perf_counter()
        with cache.lock:
            check_uniform_lengths(cache)  # the graph takes one past_length for every layer
            past = [
                tuple(np.ascontiguousarray(buffer.numpy()) for buffer in cache.buffers(layer))
                for layer in range(cache.layout.num_layers)
            ]
            outputs = runner.track(frame, past, cache.length, heads)  # type: ignore[arg-type]
        return self._track_result(outputs, {"track": (time.perf_counter() - start) * 1e3})

    def close(self) -> None:
        """Release the compiled graphs (and their memory); later calls raise ``StateError``.
        Idempotent."""
        self._runner = None

    # ------------------------------------------------------------------ helpers
    def _live_runner(self) -> GraphRunner:
        if self._runner is None:
            raise StateError(f"this {type(self).__name__} is closed")
        return self._runner

    def _to_input(self, images: np.ndarray) -> np.ndarray:
        """uint8 [N, H, W, 3] -> float32 [N, 3, H, W] in [0, 1], C-contiguous."""
        frames = check_frames(images, self.info.patch_size)
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

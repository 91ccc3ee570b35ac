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
number of cached tokens, and the graph ignores the scratch tokens after them (``ExportBackend``,
shared with ``OpenVinoBackend``).

onnxruntime is imported when a backend is created (``MissingDependencyError`` names the
``[onnx]`` extra without it). PyTorch is still needed for the ``KVCache`` itself, not to compute.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

from kvtracker_sdk.backends.export_backend import ExportBackend, export_folder
from kvtracker_sdk.backends.onnx_runtime import OnnxRunner, providers_for

__all__ = ["OnnxBackend"]


class OnnxBackend(ExportBackend):
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
        super().__init__(folder)
        runner = OnnxRunner(
            self.folder, self.manifest, providers=providers_for(device, providers), threads=threads
        )
        # the cache stays on the CPU whatever the provider: ORT reads host memory
        info = self.manifest.backend_info(
            backend="onnx", device="cpu", accelerations=runner.active_providers
        )
        self._serve(runner, info)

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
        return cls(export_folder(source), device=device, providers=providers, threads=threads)

"""``OpenVinoBackend``: the ``Backend`` contract served by OpenVINO from an exported folder.

    backend = OpenVinoBackend("da3-small-onnx/")                         # fp32, CPU
    backend = OpenVinoBackend("da3-small-onnx/", precision="bfloat16", threads=2)
    backend = openvino_backend("da3-small")   # kvtracker_sdk.export_onnx: exported once
    mapped = backend.map(keyframes)           # uint8 [N, H, W, 3] at model resolution
    result = backend.track(frame, mapped.cache, heads=HeadSet.CAMERA)

OpenVINO (Apache-2.0) runs on the CPUs, integrated GPUs and NPUs AR and robot apps ship on. This
backend serves the same export folder as ``OnnxBackend`` (``kvtracker export-onnx``; both
families), verified file by file against the manifest's sha256 before OpenVINO reads it, with
the cache as graph inputs (``ExportBackend``: the shared part). Its ``info.fingerprint`` and
``info.layout`` are the manifest's, equal to ``TorchBackend``'s and ``OnnxBackend``'s for the
same weights, and its cache is float32 on the CPU whatever the precision hint, so a tracker swaps
between torch, onnx and openvino live and maps saved by one load in the others.

``precision`` "float32" (default) computes the export's function within float rounding;
"bfloat16" is faster where the CPU has bf16 products, with a larger deviation (see
``openvino_runtime``) that grows with the map and depends on the CPU: on large DA3 maps its poses
can deviate several times more than PyTorch's bf16 while "float32" is nearly as fast (figures:
``benchmarks/README.md#figures-behind-the-code``; README, model choice). "mixed" keeps the
graphs the pose passes through (decoders, camera head) in float32 and runs the image encoder
and the dense heads in bf16: between the two in speed, about PyTorch bf16's deviation.
``kvtracker tune`` measures them on the machine at hand and keeps bf16 only within PyTorch bf16's
deviation (``backends/autotune.py``). ``info.accelerations`` reports what the plugin chose: device, precision,
threads.

openvino is imported when a backend is created (``MissingDependencyError`` names the
``[openvino]`` extra without it). PyTorch is still needed for the ``KVCache`` itself.

Waiting threads: OpenVINO's CPU plugin runs on oneTBB, whose idle workers sleep after a short
spin (no ``OMP_WAIT_POLICY`` applies to them). torch's OpenMP still copies the cache here; with
its spinning default that nobody chose (torch imported before ``kvtracker_sdk``:
``threads.spins_by_default``) the backend sets torch to one thread when it is built, so that no
spinning OpenMP thread takes a core from OpenVINO's, and logs the fix.
"""

from __future__ import annotations

import os
from collections.abc import Collection

import torch

from kvtracker_sdk.backends.export_backend import ExportBackend, export_folder
from kvtracker_sdk.backends.openvino_runtime import OpenVinoRunner
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.threads import SPINNING_FIX, spins_by_default

__all__ = ["OpenVinoBackend"]

_log = get_logger(__name__)


def _quiet_torch_threads() -> None:
    """One torch thread when torch's OpenMP spins by default (see the module docstring)."""
    if spins_by_default() and torch.get_num_threads() > 1:
        _log.warning("torch set to one thread: OpenMP spins", fix=SPINNING_FIX)
        torch.set_num_threads(1)


class OpenVinoBackend(ExportBackend):
    """Pi3 or Depth Anything 3 on OpenVINO; implements ``kvtracker_sdk.backends.base.Backend``.

    ``folder``: an export (``kvtracker export-onnx``); its files must match the sha256 digests
    of its manifest (``ModelError`` otherwise). ``device``: "cpu" (default), "gpu[:N]" or "npu"
    where OpenVINO sees one. ``precision``: "float32" (default), "bfloat16" or "float16" (the
    inference precision hint of every graph; the cache stays float32), or "mixed" (per graph:
    bf16 encoder and dense heads, fp32 decoders and camera head; ``openvino_runtime``). ``threads``: CPU inference threads
    (None: one per physical core). ``static_shapes``: track on graphs compiled for the
    current map's exact shapes (``openvino_static``; one compile, on the first frame after the
    map's keyframe count or resolution changes): None (default) = every tracking graph in
    float32, all but the tracking decoder with a bf16/f16 hint (the static decoder's bf16 poses
    deviate more; ``openvino_runtime.static_graphs``); True = every tracking graph (the fastest);
    False = none; or graph names. Measured speeds and compile times:
    ``benchmarks/README.md#figures-behind-the-code``.
    """

    def __init__(
        self,
        folder: str | os.PathLike[str],
        *,
        device: str = "cpu",
        precision: str = "float32",
        threads: int | None = None,
        static_shapes: bool | Collection[str] | None = None,
    ) -> None:
        super().__init__(folder)
        _quiet_torch_threads()
        runner = OpenVinoRunner(
            self.folder,
            self.manifest,
            device=device,
            precision=precision,
            threads=threads,
            static_shapes=static_shapes,
        )
        # the cache stays on the host whatever the device: OpenVINO reads host memory
        info = self.manifest.backend_info(
            backend="openvino", device="cpu", accelerations=runner.accelerations
        )
        self._serve(runner, info)
        self._static = runner.static

    @property
    def static_compiles(self) -> tuple[tuple[str, float], ...]:
        """The static-shape compiles so far, (graph, seconds) in order; each new map shape adds
        one for the tracking decoder (empty with ``static_shapes=False``)."""
        return () if self._static is None else tuple(self._static.compile_seconds)

    @classmethod
    def from_pretrained(
        cls,
        source: str | os.PathLike[str],
        *,
        device: str = "cpu",
        precision: str = "float32",
        threads: int | None = None,
        static_shapes: bool | Collection[str] | None = None,
    ) -> OpenVinoBackend:
        """An export folder (as ``TorchBackend.from_pretrained`` takes a checkpoint).

        A checkpoint is exported by a layer above this one: ``kvtracker_sdk.export_onnx.
        openvino_backend(checkpoint)`` exports it once into a cache folder and serves the export
        (``kvtracker track --backend openvino --weights model.safetensors`` does that).
        """
        return cls(
            export_folder(source),
            device=device,
            precision=precision,
            threads=threads,
            static_shapes=static_shapes,
        )

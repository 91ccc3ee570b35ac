"""``--backend`` / ``--weights`` / ``--device`` / ``--dtype`` -> a ``Backend`` for ``kvtracker track``.

Each runtime is imported only when chosen: the PyTorch backend loads the checkpoint (a
``.safetensors`` file, a folder holding one, or a hub id such as ``yyfz233/Pi3``); the ONNX and
OpenVINO backends load exported graphs (``kvtracker export-onnx``) from ``--weights``, or export
a checkpoint there once. OpenVINO takes ``--dtype bfloat16`` as its precision hint (its cache
stays float32) and ``--threads`` as its inference threads.
"""

from __future__ import annotations

import enum
import importlib
from pathlib import Path
from typing import TYPE_CHECKING

from kvtracker_sdk.errors import ConfigError, MissingDependencyError

if TYPE_CHECKING:
    from kvtracker_sdk.backends.base import Backend

__all__ = ["DEFAULT_WEIGHTS", "BackendKind", "ComputeDtype", "open_backend"]

DEFAULT_WEIGHTS = "yyfz233/Pi3"  # the official Pi3 checkpoint on the Hugging Face hub


class BackendKind(str, enum.Enum):
    AUTO = "auto"  # resolved by cli/tune.py's auto_choice before a backend is opened
    TORCH = "torch"
    ONNX = "onnx"
    OPENVINO = "openvino"


class ComputeDtype(str, enum.Enum):
    FLOAT32 = "float32"
    BFLOAT16 = "bfloat16"


def open_backend(
    kind: BackendKind,
    weights: str | Path,
    *,
    device: str = "cpu",
    dtype: ComputeDtype | str = "float32",
    threads: int | None = None,
) -> Backend:
    """The backend of ``kind`` over ``weights``; typed errors for missing runtimes or weights.

    ``threads`` sets torch's intra-op CPU threads (process-wide: the CLI owns the process; None:
    chosen from the free cores, ``kvtracker_sdk/threads.py``) or OpenVINO's inference threads; the
    ONNX backend chooses its own.
    """
    dtype_name = ComputeDtype(dtype).value
    if threads is not None and threads < 1:
        raise ConfigError(f"--threads must be >= 1, got {threads}")
    if kind is BackendKind.TORCH:
        try:
            from kvtracker_sdk.backends.torch_backend import TorchBackend
        except ImportError as exc:
            raise MissingDependencyError(f"the PyTorch backend cannot be imported: {exc}") from exc
        # None: the backend chooses from the free cores (kvtracker_sdk/threads.py)
        return TorchBackend.from_pretrained(
            weights, dtype=dtype_name, device=device, threads=threads
        )
    if kind is BackendKind.ONNX:
        if dtype_name != ComputeDtype.FLOAT32.value:
            raise ConfigError("the ONNX backend runs the exported graphs' dtype; drop --dtype")
        try:
            module = importlib.import_module("kvtracker_sdk.export_onnx.reuse")
        except ImportError as exc:
            raise MissingDependencyError(
                f"the ONNX backend needs onnxruntime: pip install 'kvtracker-sdk[onnx]' ({exc})"
            ) from exc
        backend: Backend = module.onnx_backend(weights, device=device)
        return backend
    if kind is BackendKind.OPENVINO:
        try:  # openvino itself is imported when the backend is made (MissingDependencyError)
            module = importlib.import_module("kvtracker_sdk.export_onnx.reuse")
        except ImportError as exc:
            raise MissingDependencyError(
                f"the OpenVINO backend cannot be imported: {exc}; pip install "
                "'kvtracker-sdk[openvino]'"
            ) from exc
        served: Backend = module.openvino_backend(
            weights, device=device, precision=dtype_name, threads=threads
        )
        return served
    raise ConfigError(f"unknown backend {kind!r}")  # pragma: no cover - typer checks the choice

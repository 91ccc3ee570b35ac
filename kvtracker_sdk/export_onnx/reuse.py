"""Checkpoints exported once and reused: ``onnx_backend(checkpoint)`` serves an ``OnnxBackend``,
``openvino_backend(checkpoint)`` an ``OpenVinoBackend`` (the same export: exporting needs the
``[onnx]`` extra once, serving it with OpenVINO only ``[openvino]``).

``exported_folder(weights)`` loads a checkpoint of either family (model name, ``.safetensors``
file, folder or hub id), and returns ``<cache_dir>/<family>-<weights fingerprint>``, exporting into it first unless an export
of the same weights is already there and its files match their recorded sha256 (a damaged or
tampered folder is exported again). The default ``cache_dir`` is
``$KVTRACKER_CACHE_DIR/onnx``, else ``$XDG_CACHE_HOME/kvtracker_sdk/onnx``, else
``~/.cache/kvtracker_sdk/onnx``. The first call for the full model takes minutes (the export is
checked against PyTorch); later calls only hash the weights.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Collection, Sequence
from pathlib import Path
from typing import Any

from kvtracker_sdk.backends.onnx import OnnxBackend
from kvtracker_sdk.backends.onnx_integrity import verify_files
from kvtracker_sdk.backends.onnx_manifest import MANIFEST_NAME, read_manifest
from kvtracker_sdk.backends.openvino import OpenVinoBackend
from kvtracker_sdk.errors import ModelError
from kvtracker_sdk.export_onnx.exporter import export_model
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.models.registry import load_model

__all__ = ["default_cache_dir", "exported_folder", "onnx_backend", "openvino_backend"]

_log = get_logger(__name__)


def default_cache_dir() -> Path:
    """Where exports of checkpoints are kept (see the module docstring)."""
    if root := os.environ.get("KVTRACKER_CACHE_DIR"):
        return Path(root) / "onnx"
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "kvtracker_sdk" / "onnx"


def exported_folder(
    weights: str | os.PathLike[str],
    *,
    cache_dir: str | os.PathLike[str] | None = None,
    on_export: Callable[[Path], None] | None = None,
) -> Path:
    """The export folder of a checkpoint, made on first use (see the module docstring).

    ``on_export(folder)`` is called only when an export actually starts (not when a cached one
    is reused): a caller can announce the minutes it takes.
    """
    loaded = load_model(weights)
    folder = Path(cache_dir or default_cache_dir()) / f"{loaded.family}-{loaded.fingerprint}"
    try:
        manifest = read_manifest(folder)
        if manifest.weights_fingerprint == loaded.fingerprint:
            verify_files(folder, manifest.sha256)
            return folder
    except ModelError as exc:  # absent, incomplete, damaged or from another SDK: export again
        _log.info("cached onnx export unusable", folder=str(folder), reason=str(exc)[:300])
    _log.info("exporting checkpoint to onnx once", weights=str(loaded.path), folder=str(folder))
    if on_export is not None:
        on_export(folder)
    export_model(
        loaded.model,
        folder,
        weights_fingerprint=loaded.fingerprint,
        name=loaded.name,
        overwrite=True,
    )
    return folder


def onnx_backend(
    source: str | os.PathLike[str],
    *,
    device: str = "cpu",
    providers: Sequence[Any] | None = None,
    threads: int | None = None,
    cache_dir: str | os.PathLike[str] | None = None,
    on_export: Callable[[Path], None] | None = None,
) -> OnnxBackend:
    """An ``OnnxBackend`` over an export folder, or over a checkpoint of either family (model
    name such as ``da3-small``, file, folder or hub id) exported on first use into
    ``cache_dir`` (``exported_folder``; that first call takes minutes for the full model).
    Deployments ship the export folder. ``on_export``: as in ``exported_folder``."""
    folder = _export_of(source, cache_dir, on_export)
    return OnnxBackend(folder, device=device, providers=providers, threads=threads)


def openvino_backend(
    source: str | os.PathLike[str],
    *,
    device: str = "cpu",
    precision: str = "float32",
    threads: int | None = None,
    cache_dir: str | os.PathLike[str] | None = None,
    static_shapes: bool | Collection[str] | None = None,
    on_export: Callable[[Path], None] | None = None,
) -> OpenVinoBackend:
    """An ``OpenVinoBackend`` over an export folder, or over a checkpoint exported on first use
    into ``cache_dir`` as ``onnx_backend`` does (the same folder serves both runtimes).

        backend = openvino_backend("da3-small", precision="bfloat16", threads=2)
    """
    folder = _export_of(source, cache_dir, on_export)
    return OpenVinoBackend(
        folder, device=device, precision=precision, threads=threads, static_shapes=static_shapes
    )


def _export_of(
    source: str | os.PathLike[str],
    cache_dir: str | os.PathLike[str] | None,
    on_export: Callable[[Path], None] | None = None,
) -> Path:
    """``source`` itself when it is an export folder, else its checkpoint's export."""
    folder = Path(source)
    if not (folder / MANIFEST_NAME).is_file():
        folder = exported_folder(source, cache_dir=cache_dir, on_export=on_export)
    return folder

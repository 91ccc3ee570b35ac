"""Export a network of any model family (Pi3, Depth Anything 3) to a folder of ONNX graphs +
``manifest.json`` that ``OnnxBackend`` serves.

    from kvtracker_sdk.export_onnx import export_onnx
    manifest = export_onnx("pi3-onnx/", weights="model.safetensors")      # or a hub id / folder
    manifest = export_onnx("da3-onnx/", weights="da3-small")              # a model name
    manifest = export_onnx("tiny-onnx/", config=Pi3Config(...), seed=0)   # random weights

Steps: every graph of the family (its record's ``graphs``, ``models/<family>/graph_specs.py``) goes
through the dynamo
exporter (``torch.onnx.export(dynamo=True)``) with dynamic frames, patch grid and cache length;
an export that fixed one of those sizes is refused. The weights move to one shared
``weights.bin`` (``external_data.py``); then ONNX Runtime runs a mapping pass and a tracking
pass over the new graphs and the outputs, in the SDK's conventions, are compared with
``TorchBackend``'s (the family record's ``map`` / ``track``) on the same inputs — the tracking cache's
scratch holds NaN, so a graph reading past the cached tokens fails. The largest differences go
to the manifest (``check``); an export that differs by more than 1e-3 of the outputs'
magnitude is refused.

The folder is written next to its destination and renamed into place at the end: an existing
export is only replaced (``overwrite=True``) by a complete, checked one.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import logging
import os
import shutil
import tempfile
import warnings
from collections.abc import Iterator
from datetime import datetime, timezone
from importlib.metadata import version
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from torch import nn

from kvtracker_sdk._version import __version__
from kvtracker_sdk.backends.onnx_integrity import file_digests
from kvtracker_sdk.backends.onnx_manifest import WEIGHTS_NAME, GraphSpec, OnnxManifest
from kvtracker_sdk.backends.onnx_runtime import OnnxRunner, import_onnxruntime
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.errors import ConfigError, MissingDependencyError, ModelError
from kvtracker_sdk.export_onnx.graph_def import GraphDef, dynamic_shapes
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.models.checkpoint_utils import weights_fingerprint as hash_weights
from kvtracker_sdk.models.family import Network
from kvtracker_sdk.models.registry import family_of, family_of_config, load_model
from kvtracker_sdk.types import HeadSet

__all__ = ["DEFAULT_CHECK_SIZE", "DEFAULT_OPSET", "export_model", "export_onnx"]

# ONNX Runtime >= 1.17; opset 23 maps SDPA to `Attention`, which ran slower on the CPU
# (benchmarks/README.md#figures-behind-the-code)
DEFAULT_OPSET = 20
DEFAULT_CHECK_SIZE = (126, 168)  # (H, W) of the check: small, not square, a 9 x 12 patch grid
_CHECK_TOLERANCE = 1e-3  # max |ORT - PyTorch| relative to the output's largest magnitude
_NOISY_LOGGERS = ("torch.onnx", "torch.export", "onnx_ir", "onnxscript")
_log = get_logger(__name__)


def export_onnx(
    out_dir: str | os.PathLike[str],
    *,
    weights: str | os.PathLike[str] | None = None,
    config: Any | None = None,
    seed: int = 0,
    check_size: tuple[int, int] = DEFAULT_CHECK_SIZE,
    opset: int = DEFAULT_OPSET,
    overwrite: bool = False,
) -> OnnxManifest:
    """Export a checkpoint of either family (model name such as ``da3-small``, ``.safetensors``
    file, folder or hub id) or, with ``weights=None``, a ``config`` with random weights (seeded;
    for tests and benchmarks) to ``out_dir``."""
    _check_destination(Path(out_dir), overwrite)  # before minutes of loading and exporting
    if weights is not None:
        loaded = load_model(weights, config=config)
        model = loaded.model
        fingerprint, name = loaded.fingerprint, loaded.name
    elif config is not None:
        torch.manual_seed(seed)
        family = family_of_config(config)  # ModelError for anything but a family's config
        model = family.build(config)
        fingerprint, name = hash_weights(model.state_dict()), family.model_name(model)
    else:
        raise ConfigError("export_onnx needs weights (a checkpoint) or a config (random weights)")
    return export_model(
        model,
        out_dir,
        weights_fingerprint=fingerprint,
        name=name,
        check_size=check_size,
        opset=opset,
        overwrite=overwrite,
    )


def export_model(
    model: nn.Module,
    out_dir: str | os.PathLike[str],
    *,
    weights_fingerprint: str | None = None,
    name: str | None = None,
    check_size: tuple[int, int] = DEFAULT_CHECK_SIZE,
    opset: int = DEFAULT_OPSET,
    overwrite: bool = False,
) -> OnnxManifest:
    """Export an fp32 network of a model family (weights as loaded; not modified) to
    ``out_dir``; see the module doc.

    ``weights_fingerprint`` defaults to the hash of ``model.state_dict()`` and ``name`` to the
    architecture's (``models.registry.model_name``) — what ``TorchBackend(model)`` reports, so
    both backends share ``info.fingerprint``.
    """
    _require_exporter()
    destination = Path(out_dir)
    family = family_of(model)  # ModelError for networks of no family
    graphs = family.graphs(model)  # ConfigError for what cannot be exported
    network = cast(Network, model)
    if network.compute_dtype != torch.float32:
        raise ConfigError(f"export an fp32 model, got {network.compute_dtype}")
    patch = network.config.patch_size
    if any(side <= patch or side % patch for side in check_size):
        raise ConfigError(f"check_size {check_size} must be multiples of {patch}, above {patch}")
    _check_destination(destination, overwrite)
    destination.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{destination.name}.", dir=destination.parent))
    staging.chmod(0o755)  # mkdtemp makes it private; the export is an ordinary folder
    try:
        manifest = _export_into(
            model.eval(),
            graphs,
            staging,
            weights_fingerprint=weights_fingerprint or hash_weights(model.state_dict()),
            name=name or family.model_name(model),
            check_size=check_size,
            opset=opset,
        )
        _replace_folder(staging, destination)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    _log.info("onnx export written", folder=str(destination), check=manifest.check)
    return manifest


def _check_destination(destination: Path, overwrite: bool) -> None:
    if destination.exists() and not overwrite:
        raise ConfigError(f"{destination} exists: pass overwrite=True (--overwrite) to replace it")


def _require_exporter() -> None:
    for module in ("onnx", "onnxscript", "onnx_ir"):
        try:
            importlib.import_module(module)
        except ImportError as exc:
            raise MissingDependencyError.for_extra(
                "onnx", f"exporting to ONNX needs {module} ({exc})") from exc
    import_onnxruntime()  # the export is checked with ONNX Runtime


def _export_into(
    model: nn.Module,
    graphs: list[GraphDef],
    folder: Path,
    *,
    weights_fingerprint: str,
    name: str,
    check_size: tuple[int, int],
    opset: int,
) -> OnnxManifest:
    import onnx_ir as ir

    from kvtracker_sdk.export_onnx.external_data import SharedWeightsWriter

    config = cast(Network, model).config
    family = family_of(model)
    examples = family.example_inputs(model, check_size)
    specs: dict[str, GraphSpec] = {}
    with SharedWeightsWriter(folder, WEIGHTS_NAME) as weights:
        for graph in graphs:
            _log.info("exporting graph", graph=graph.name)
            onnx_model = _export_graph(model, graph, examples[graph.name], opset)
            added = weights.externalize(onnx_model)
            ir.save(onnx_model, folder / f"{graph.name}.onnx")
            _log.info("graph exported", graph=graph.name, new_weight_bytes=added)
            specs[graph.name] = GraphSpec(
                file=f"{graph.name}.onnx", inputs=graph.inputs, outputs=graph.outputs
            )
        weights_bytes = weights.size
    files = [WEIGHTS_NAME, *(spec.file for spec in specs.values())]
    digests = file_digests(folder, files)  # verified by every backend that loads the folder
    provisional = OnnxManifest(
        sdk_version=__version__,
        created_utc=datetime.now(timezone.utc).isoformat(timespec="seconds"),
        family=family.name,
        model=name,
        config=config.model_dump(),
        config_hash=config.config_hash,
        weights_fingerprint=weights_fingerprint,
        fingerprint="",
        patch_size=config.patch_size,
        extra_tokens_per_frame=family.extra_tokens_per_frame(model),
        layout=family.cache_layout(model).to_dict(),
        opset=opset,
        check_resolution=check_size,
        weights_bytes=weights_bytes,
        sha256=digests,
        exporter={name: version(name) for name in ("torch", "onnx", "onnxscript", "onnx-ir")},
        graphs=specs,
    )
    identity = provisional.backend_info(device="cpu", accelerations=()).fingerprint
    manifest = provisional.model_copy(update={"fingerprint": identity})
    manifest = manifest.model_copy(update={"check": _check(model, folder, manifest, check_size)})
    manifest.write(folder)
    return manifest


def _export_graph(
    model: nn.Module, graph: GraphDef, args: tuple[Any, ...], opset: int) -> Any:
    """One graph through the dynamo exporter; its dims renamed after ``graph``'s specs.

    ``ModelError`` if the exporter fixed a dim the specs declare dynamic (a Python computation
    on a size, e.g. ``torch.linspace(..., steps=size)``, does that silently): the graph would
    then serve one resolution or cache length only.
    """
    import onnx_ir as ir

    with _quiet_exporter(), torch.no_grad():
        program = torch.onnx.export(
            graph.module(model).eval(),
            args,
            dynamo=True,
            dynamic_shapes=dynamic_shapes(graph, cast(Network, model).config.patch_size),
            input_names=[spec.name for spec in graph.inputs],
            output_names=[spec.name for spec in graph.outputs],
            opset_version=opset,
            optimize=True,
            verbose=False,
        )
    assert program is not None  # the dynamo exporter always returns its program
    onnx_model = program.model
    onnx_model.graph.name = graph.name
    for node in onnx_model.graph:  # drop the exporter's stack traces (they hold local paths)
        for key in [key for key in node.metadata_props if key != "namespace"]:
            del node.metadata_props[key]
    values = [*onnx_model.graph.inputs, *onnx_model.graph.outputs]
    specs = [*graph.inputs, *graph.outputs]
    if [value.name for value in values] != [spec.name for spec in specs]:
        raise ModelError(f"graph {graph.name}: the exporter changed the inputs/outputs")
    for value, spec in zip(values, specs, strict=True):
        exported = list(value.shape) if value.shape is not None else []
        fixed = [
            dim
            for dim, got in zip(spec.shape, exported, strict=False)
            if isinstance(dim, str) and isinstance(got, int)
        ]
        if fixed or len(exported) != len(spec.shape):
            raise ModelError(
                f"graph {graph.name}: {value.name} has shape {exported}, expected {spec.shape} "
                f"(the exporter fixed {fixed}: some code computes on a size in Python)"
            )
        value.shape = ir.Shape([d if isinstance(d, int) else ir.SymbolicDim(d) for d in spec.shape])
    return onnx_model


@contextlib.contextmanager
def _quiet_exporter() -> Iterator[None]:
    """The exporter prints its progress, warns (about axis names, torchvision) and logs every
    folded constant: route the printed text to a debug log and mute the rest meanwhile."""
    stdout = io.StringIO()
    loggers = [logging.getLogger(name) for name in _NOISY_LOGGERS]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.ERROR)
    try:
        with contextlib.redirect_stdout(stdout), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        for logger, level in zip(loggers, levels, strict=True):
            logger.setLevel(level)
    if stdout.getvalue():
        _log.debug("torch.onnx output", text=stdout.getvalue())


@torch.no_grad()
def _check(
    model: nn.Module, folder: Path, manifest: OnnxManifest, size: tuple[int, int]
) -> dict[str, float]:
    """Max |ORT - PyTorch| per output of a mapping pass (2 keyframes) and a tracking pass, in
    the SDK's conventions (what the two backends return)."""
    family = family_of(model)
    generator = torch.Generator().manual_seed(1)
    images = torch.rand(3, 3, *size, generator=generator)
    mapped = family.map(model, images[:2])
    cache = KVCache.from_layers(
        mapped.keys,
        mapped.values,
        layout=manifest.cache_layout,
        tokens_per_frame=mapped.tokens_per_frame,
        keyframe_ids=range(2),
    )
    _fill_scratch(cache, float("nan"))
    tracked = family.track(model, images[2:], cache, HeadSet.ALL)
    _fill_scratch(cache, float("nan"))  # the PyTorch pass wrote the query's K/V there

    runner = OnnxRunner(folder, manifest)
    ort_map, keys, values = runner.map(images[:2].numpy())
    past = [(k.numpy(), v.numpy()) for k, v in map(cache.buffers, range(cache.layout.num_layers))]
    ort_track = runner.track(images[2:].numpy(), past, cache.length, HeadSet.ALL)
    pairs: dict[str, tuple[Any, Any]] = {
        "map.camera_poses": (ort_map.poses, mapped.frames.poses),
        "map.confidence": (ort_map.confidence, mapped.frames.confidence),
        "map.local_points": (ort_map.local_points, mapped.frames.local_points),
        "map.keys": (np.stack(keys), torch.stack(mapped.keys).numpy()),
        "map.values": (np.stack(values), torch.stack(mapped.values).numpy()),
        "track.camera_poses": (ort_track.poses, tracked.poses),
        "track.confidence": (ort_track.confidence, tracked.confidence),
        "track.local_points": (ort_track.local_points, tracked.local_points),
    }
    errors: dict[str, float] = {}
    for name, (got, expected) in pairs.items():
        truth = np.asarray(expected, dtype=np.float64)
        error = float(np.abs(np.asarray(got, dtype=np.float64) - truth).max())
        errors[name] = error
        if not error <= _CHECK_TOLERANCE * max(1.0, float(np.abs(truth).max())):
            raise ModelError(
                f"the exported graphs disagree with PyTorch on {name}: max |diff| {error:.3g}"
            )
    return errors


def _fill_scratch(cache: KVCache, value: float) -> None:
    for layer in range(cache.layout.num_layers):
        for buffer in cache.buffers(layer):
            buffer[:, :, cache.length :] = value


def _replace_folder(staging: Path, destination: Path) -> None:
    """Move the finished export into place; an old export is removed only after that."""
    old = None
    if destination.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{destination.name}.old.", dir=destination.parent))
        os.replace(destination, old / destination.name)
    os.replace(staging, destination)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)

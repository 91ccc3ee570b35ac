"""``manifest.json`` of an exported ONNX folder: what each graph takes and returns, and whose it is.

An export folder (``kvtracker export-onnx``) holds one ``.onnx`` file per graph, one
``weights.bin`` with every graph's weights (external data, deduplicated across graphs: the
mapping and tracking decoders share theirs) and this manifest. Reading it needs no onnxruntime: a
folder is validated before any session is created.

Graphs of a Pi3 export (F frames, h x w patches of ``patch_size`` px, R decoder registers, L
cached layers; float32 unless noted)::

    encoder         images [F, 3, H, W] in [0, 1]             -> patch_tokens [F, h, w, dim]
    decoder_map     patch_tokens [N, h, w, dim]                 -> hidden_registers [N, R, 2*dim],
                                                                   hidden_patches [N, h, w, 2*dim],
                                                                   present.{i}.key/value [1, heads, N*T, head_dim]
    decoder_track   patch_tokens [1, h, w, dim], past_length int64 [],
                    past_key_values.{i}.key/value [1, heads, past_capacity, head_dim]
                                                                -> hidden_registers, hidden_patches (F = 1)
    head_camera     hidden_registers, hidden_patches            -> rotation_raw [F, 9], translation [F, 3]
    head_conf       hidden_registers, hidden_patches            -> conf_logits [F, H, W]
    head_points     hidden_registers, hidden_patches            -> local_points [F, H, W, 3] (camera frame)

Graphs of a Depth Anything 3 export (C the backbone width, T = 1 + h*w)::

    encoder         images [F, 3, H, W] in [0, 1]             -> patch_tokens [F, h, w, C]
    decoder_map     patch_tokens [N, h, w, C]                   -> camera_tokens [N, 2C],
                                                                   features.{0..3} [N, h, w, 2C],
                                                                   present.{i}.key/value [1, heads, N*T, head_dim]
    decoder_track   patch_tokens [1, h, w, C], past_length, past_key_values.{i}.key/value
                                                                -> camera_tokens, features.{0..3} (F = 1)
    head_camera     camera_tokens                               -> pose_enc [F, 9] (t, quaternion xyzw, fov_h, fov_w)
    head_depth      features.{0..3}                             -> depth [F, H, W], depth_conf [F, H, W] (>= 1)

Keyframe 0 of a DA3 mapping pass carries the reference camera token (the world frame); the
tracking query carries the non-reference one. Each head graph's inputs are named after the
decoder outputs it reads, so a runtime feeds them by name whatever the family.

``{i}`` is the ordinal of a cached (global) layer, as in ``KVCache.keys(i)``. The tracking
decoder reads tokens ``[:past_length]`` of its past inputs and ignores the rest: a ``KVCache``
buffer (cached tokens followed by scratch capacity) is passed as it is, without a copy; a compact
past (``past_length`` = its length) works too. Every spatial size is dynamic: one export serves
any resolution whose sides are multiples of ``patch_size``.
"""

from __future__ import annotations

import json
from pathlib import Path, PurePosixPath
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from kvtracker_sdk.backends.base import BackendInfo
from kvtracker_sdk.cache.kv_cache import CacheLayout
from kvtracker_sdk.errors import ModelError
from kvtracker_sdk.models.graph_io import (
    TensorSpec,
    past_key_name,
    past_value_name,
    present_key_name,
    present_value_name,
)
from kvtracker_sdk.models.registry import FAMILIES

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "FAMILY_GRAPHS",
    "MANIFEST_NAME",
    "WEIGHTS_NAME",
    "GraphSpec",
    "OnnxManifest",
    "TensorSpec",
    "past_key_name",
    "past_value_name",
    "present_key_name",
    "present_value_name",
    "read_manifest",
]

FORMAT_NAME = "kvtracker-onnx"
FORMAT_VERSION = 2  # bump on any change an older reader would misread (2: file sha256)
MANIFEST_NAME = "manifest.json"
WEIGHTS_NAME = "weights.bin"
# graphs of an export, per family (``manifest.family``), in the order they run: the family records'
FAMILY_GRAPHS: dict[str, tuple[str, ...]] = {
    name: family.graph_names for name, family in FAMILIES.items()
}


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class GraphSpec(_Frozen):
    file: str  # relative to the export folder
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]


class OnnxManifest(_Frozen):
    """Everything a runtime needs to serve the graphs, and the identity of the function."""

    format: str = FORMAT_NAME
    format_version: int = FORMAT_VERSION
    sdk_version: str
    created_utc: str
    family: str  # "pi3", "da3", ...: a key of ``models.registry.FAMILIES``
    model: str  # "pi3", "da3-small", ... for released architectures, "<family>-custom" otherwise
    config: dict[str, Any]  # the architecture (Pi3Config / DA3Config .model_dump())
    config_hash: str
    weights_fingerprint: str
    fingerprint: str  # BackendInfo.fingerprint of these weights: equal to TorchBackend's
    patch_size: int
    extra_tokens_per_frame: int
    layout: dict[str, Any]  # CacheLayout.to_dict()
    dtype: str = "float32"
    opset: int
    resolution: str = "dynamic"  # any H, W that are positive multiples of patch_size
    check_resolution: tuple[int, int]  # (H, W) of the export-time ORT-vs-PyTorch check
    check: dict[str, float] = Field(default_factory=dict)  # output -> max |ORT - PyTorch|
    weights_file: str = WEIGHTS_NAME
    weights_bytes: int
    sha256: dict[str, str]  # file (every graph and the weights) -> hex sha256, see onnx_integrity
    exporter: dict[str, str] = Field(default_factory=dict)  # torch / onnx / onnxscript versions
    graphs: dict[str, GraphSpec]

    @property
    def cache_layout(self) -> CacheLayout:
        return CacheLayout.from_dict(self.layout)

    def backend_info(
        self, *, device: str, accelerations: tuple[str, ...], backend: str = "onnx"
    ) -> BackendInfo:
        """The ``BackendInfo`` of a runtime (``backend``: "onnx", "openvino") serving these
        graphs: every runtime's has this manifest's fingerprint and layout."""
        return BackendInfo(
            backend=backend,
            model=self.model,
            family=self.family,
            config_hash=self.config_hash,
            weights_fingerprint=self.weights_fingerprint,
            patch_size=self.patch_size,
            extra_tokens_per_frame=self.extra_tokens_per_frame,
            layout=self.cache_layout,
            dtype=self.dtype,
            device=device,
            accelerations=accelerations,
        )

    def write(self, folder: Path) -> Path:
        path = folder / MANIFEST_NAME
        path.write_text(self.model_dump_json(indent=2) + "\n")
        return path


def _inside(folder: Path, name: str) -> bool:
    """Whether ``name`` is a relative path that stays inside ``folder`` (no absolute path, no
    ``..``, no symbolic link leading out)."""
    relative = PurePosixPath(name)
    if relative.is_absolute() or ".." in relative.parts or "\\" in name or ":" in name:
        return False
    try:
        return (folder / relative).resolve().is_relative_to(folder.resolve())
    except (OSError, ValueError, RuntimeError):  # unresolvable, NUL byte, symlink loop
        return False


def read_manifest(folder: str | Path) -> OnnxManifest:
    """Read and validate ``folder/manifest.json``; ``ModelError`` says what is wrong.

    Checks the format name and version, the family, that every graph of the family and the
    weights file exist inside the folder and have a recorded sha256 (verified by the backend,
    ``onnx_integrity``), and that
    the recorded fingerprint is the one the recorded identity hashes to (a hand-edited or
    mismatched manifest would otherwise let caches cross models), and that its other claims
    (config hash, graph specs, layout, weights size) hold (``onnx_claims``).
    """
    folder = Path(folder)
    path = folder / MANIFEST_NAME
    if not path.is_file():
        raise ModelError(
            f"{folder} is not an ONNX export (no {MANIFEST_NAME}): create one with "
            "`kvtracker export-onnx --weights CHECKPOINT --out DIR`"
        )
    try:
        raw = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError) as exc:  # ValueError: JSON, UTF-8 errors
        raise ModelError(f"cannot read {path}: {str(exc)[:200]}") from exc
    if not isinstance(raw, dict) or raw.get("format") != FORMAT_NAME:
        raise ModelError(f"{path} is not a {FORMAT_NAME} manifest")
    if raw.get("format_version") != FORMAT_VERSION:
        raise ModelError(
            f"{path} has format version {raw.get('format_version')}, this SDK reads version "
            f"{FORMAT_VERSION}: re-export the model with this SDK"
        )
    try:
        manifest = OnnxManifest.model_validate(raw)
    except ValidationError as exc:
        raise ModelError(f"{path} is malformed: {exc}") from exc
    if manifest.family not in FAMILY_GRAPHS:
        raise ModelError(
            f"{path} is an export of family {manifest.family!r}; this SDK serves "
            f"{sorted(FAMILY_GRAPHS)}"
        )
    missing = sorted(set(FAMILY_GRAPHS[manifest.family]) - set(manifest.graphs))
    if missing:
        raise ModelError(f"{path} lists no graph for {missing}")
    files = [manifest.weights_file, *(spec.file for spec in manifest.graphs.values())]
    outside = [name for name in files if not _inside(folder, name)]
    if outside:
        raise ModelError(f"{path} names files outside its folder: {outside}")
    absent = [name for name in files if not (folder / name).is_file()]
    if absent:
        raise ModelError(f"{folder} is incomplete: missing {absent}")
    if set(manifest.sha256) != set(files):
        raise ModelError(f"{path}: its sha256 entries must cover exactly the files {files}")
    identity = manifest.backend_info(device="cpu", accelerations=()).fingerprint
    if identity != manifest.fingerprint:
        raise ModelError(
            f"{path}: fingerprint {manifest.fingerprint} does not match its family, config "
            f"hash and weights fingerprint (which give {identity})"
        )
    from kvtracker_sdk.backends.onnx_claims import check_manifest_claims  # imports this module

    check_manifest_claims(folder, manifest)
    return manifest

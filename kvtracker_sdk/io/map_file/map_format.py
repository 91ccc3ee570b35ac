"""The ``.kvmap`` header: :class:`MapInfo`, its encoding, and validation of raw header bytes.

A map file is a safetensors file: an 8-byte little-endian header length ``n``, ``n`` bytes of
UTF-8 JSON (tensor name -> dtype, shape, data offsets; plus ``__metadata__``, a str -> str map),
then the tensor bytes. Our ``__metadata__`` holds every scalar of the map (values that are not
plain strings are nested JSON), the sha256 of each tensor's bytes, and ``metadata_sha256`` over
the other metadata entries, so a flipped byte in the tracker config or the gauge is caught, not
silently loaded.

This module does no file I/O: it builds the metadata for a :class:`MapInfo`, and turns raw header
bytes back into a validated ``MapInfo`` — checking everything that can be checked without the
tensor data: format name, version range, header checksum, fields and their types, and that the
tensor table matches the declared layout exactly and tiles the file's data section.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime
from types import MappingProxyType
from typing import Any

import numpy as np

from kvtracker_sdk.cache.backend_info import BackendInfo
from kvtracker_sdk.cache.kv_cache import CacheLayout
from kvtracker_sdk.cache.quantization import QUANTIZED_STORAGES
from kvtracker_sdk.config import TrackingMode
from kvtracker_sdk.errors import InputError, MapCorruptedError, MapFormatError, MapVersionError
from kvtracker_sdk.geometry.camera import Camera, IntrinsicsSource
from kvtracker_sdk.geometry.se3 import check_rigid
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.io.map_file.image_codec import PNG, RAW, max_png_bytes
from kvtracker_sdk.io.map_file.keyframe_codec import FULL, KEYFRAME_ENCODINGS
from kvtracker_sdk.io.map_file.map_schema import (
    CACHE_DTYPES,
    FORMAT_NAME,
    FORMAT_VERSION,
    GAUGE_SCALE_RANGE,
    IMAGE_BYTES_FIELD,
    IMAGE_CODEC_FIELD,
    IMAGE_CODEC_VERSION,
    KEYFRAME_ENCODING_FIELD,
    LAYER_LENGTHS_FIELD,
    LEGACY_PREPROCESSING,
    MAX_GENERATION,
    MAX_WORLD_TRANSLATION,
    MODE_IN_CONFIG_VERSION,
    OLDEST_READABLE_VERSION,
    PREPROCESSING_FIELD,
    PRUNED_FORMAT_VERSION,
    QUANTIZATION_FIELD,
    QUANTIZED_CACHE_DTYPES,
    RIGID_ATOL,
    WORLD_FIELD,
    TensorSpec,
    check_tensor_table,
    tensor_schema,
)
from kvtracker_sdk.world import MapWorld, ScaleSource

__all__ = [
    "MapInfo",
    "encode_metadata",
    "gauge_problem",
    "metadata_digest",
    "parse_header",
    "quantization_description",
]

_DIGEST_KEY = "metadata_sha256"
_JSON_NAMES: dict[type, str] = {dict: "object", list: "array"}
_MODES = frozenset(mode.value for mode in TrackingMode)
_REQUIRED = (
    "format", "format_version", "sdk_version", "created_utc", "backend", "resolution", "dtype",
    "layout", "tracker_config", "keyframe_ids", "cache_keyframe_ids", "generation",
    "gauge", "user_metadata", "tensor_sha256", _DIGEST_KEY,
)  # fmt: skip
_MODE_FIELD = "mode"  # versions 1-3 only: version 4 keeps the mode in the tracker config


@dataclass(frozen=True, eq=False)
class MapInfo:
    """Everything a map file's header says, parsed and validated (no tensor data read).

    ``backend`` is the :class:`BackendInfo` of the backend that saved the map; its
    ``fingerprint`` (family + config hash + weights) decides which backends may load it.
    """

    format_version: int
    sdk_version: str
    created_utc: datetime  # timezone-aware, UTC
    backend: BackendInfo
    resolution: tuple[int, int]  # (H, W) model input, pixels
    dtype: str  # cache storage name, a key of CACHE_DTYPES (int8 / float8_e4m3fn: quantised)
    tokens_per_frame: int
    mode: str  # tracking mode of the session that saved the map ("scene", "object")
    # the tracker configuration saved with the map (a JSON object), parsed once from the header
    tracker_config: Mapping[str, Any]
    keyframe_ids: tuple[int, ...]  # order of the per-keyframe tensors
    cache_keyframe_ids: tuple[int, ...]  # order of the keyframes along the cache's token axis
    generation: int
    gauge: Sim3  # raw frame of the cache's mapping pass -> world frame
    user_metadata: Mapping[str, str]
    tensor_sha256: Mapping[str, str]  # tensor name -> hex sha256 of its bytes
    file_size: int = 0  # bytes on disk (0 until written)
    # what prepared the keyframe images (kvtracker_sdk.preprocess); optional in the header:
    # maps saved before it was recorded were made by the legacy one
    preprocessing: str = LEGACY_PREPROCESSING
    # the session's input-image intrinsics and where they came from (optional header "camera")
    camera: Camera | None = None
    camera_source: IntrinsicsSource | None = None
    # a pruned map: tokens kept per cached layer (optional header "layer_lengths"); None = all
    layer_lengths: tuple[int, ...] | None = None
    # how the keyframe arrays are stored (optional header "keyframe_encoding", version 3):
    # "full" (absent) or a compact encoding of io/map_file/keyframe_codec.py
    keyframe_encoding: str = FULL
    # the world frame's units and axes (optional header "world"; absent = MapWorld())
    world: MapWorld = MapWorld()
    # how the keyframe images are stored (version 4, io/map_file/image_codec.py): "raw" pixels,
    # or "png" files of these lengths in bytes (keyframe order)
    image_codec: str = RAW
    image_bytes: tuple[int, ...] | None = None

    @property
    def layout(self) -> CacheLayout:
        return self.backend.layout

    @property
    def tracker_config_json(self) -> str:
        """The saved tracker configuration as JSON text (keys sorted)."""
        return json.dumps(dict(self.tracker_config), sort_keys=True)

    @property
    def fingerprint(self) -> str:
        return self.backend.fingerprint

    @property
    def num_keyframes(self) -> int:
        return len(self.keyframe_ids)

    @property
    def quantized(self) -> bool:
        return self.dtype in QUANTIZED_CACHE_DTYPES

    @property
    def cache_nbytes(self) -> int:
        """Bytes of the stored K/V (all layers; quantised: data and scales)."""
        return sum(
            spec.nbytes
            for name, spec in self.tensor_schema().items()
            if name.startswith("layers.") and spec.dtype != "I64"  # not a pruned map's indices
        )

    def tensor_schema(self) -> dict[str, TensorSpec]:
        """Name -> (safetensors dtype, shape) of every tensor this header declares."""
        return tensor_schema(
            self.layout, self.dtype, self.num_keyframes, self.tokens_per_frame, self.resolution,
            self.layer_lengths, self.keyframe_encoding, self.image_bytes,
        )  # fmt: skip


def quantization_description(dtype: str) -> dict[str, str]:
    """The ``cache_quantization`` header value of a quantised cache dtype: what the scales are."""
    scheme = QUANTIZED_STORAGES[dtype]
    return {
        "scale_dtype": str(scheme.scale_dtype).removeprefix("torch."),
        "key_scale": scheme.key_axis,
        "value_scale": scheme.value_axis,
    }


def _dumps(value: Any) -> str:
    return json.dumps(value, separators=(",", ":"), allow_nan=False)


def metadata_digest(metadata: Mapping[str, str]) -> str:
    """sha256 of the canonical JSON of every metadata entry except the digest itself."""
    body = {key: value for key, value in metadata.items() if key != _DIGEST_KEY}
    return hashlib.sha256(
        json.dumps(body, sort_keys=True, separators=(",", ":")).encode()
    ).hexdigest()


def encode_metadata(info: MapInfo) -> dict[str, str]:
    """The safetensors ``__metadata__`` (str -> str) of ``info``, sealed with its digest."""
    b = info.backend
    backend = {
        "backend": b.backend, "model": b.model, "family": b.family, "config_hash": b.config_hash,
        "weights_fingerprint": b.weights_fingerprint, "fingerprint": b.fingerprint,
        "patch_size": b.patch_size, "extra_tokens_per_frame": b.extra_tokens_per_frame,
        "dtype": b.dtype, "device": b.device, "accelerations": list(b.accelerations),
    }  # fmt: skip
    layout = {**b.layout.to_dict(), "tokens_per_frame": info.tokens_per_frame}
    gauge = {
        "rotation": info.gauge.rotation.tolist(),
        "translation": info.gauge.translation.tolist(),
        "scale": info.gauge.scale,
    }
    metadata = {
        "format": FORMAT_NAME,
        "format_version": str(info.format_version),
        "sdk_version": info.sdk_version,
        "created_utc": info.created_utc.isoformat(),
        "backend": _dumps(backend),
        "resolution": _dumps(list(info.resolution)),
        "dtype": info.dtype,
        "layout": _dumps(layout),
        "tracker_config": info.tracker_config_json,
        "keyframe_ids": _dumps(list(info.keyframe_ids)),
        "cache_keyframe_ids": _dumps(list(info.cache_keyframe_ids)),
        "generation": str(info.generation),
        # JSON floats are written with repr, so R, t and s read back bit for bit (a 4x4 sR
        # matrix would not give back R and s exactly)
        "gauge": _dumps(gauge),
        "user_metadata": _dumps(dict(info.user_metadata)),
        "tensor_sha256": _dumps(dict(info.tensor_sha256)),
        PREPROCESSING_FIELD: info.preprocessing,
    }
    if info.format_version < MODE_IN_CONFIG_VERSION:
        metadata[_MODE_FIELD] = info.mode
    if info.image_codec != RAW:  # version 4: keyframe images as PNG files
        metadata[IMAGE_CODEC_FIELD] = info.image_codec
        metadata[IMAGE_BYTES_FIELD] = _dumps(list(info.image_bytes or ()))
    if info.layer_lengths is not None:  # optional: only pruned maps have it
        metadata[LAYER_LENGTHS_FIELD] = _dumps(list(info.layer_lengths))
    if info.keyframe_encoding != FULL:  # version 3: a compact keyframe payload
        metadata[KEYFRAME_ENCODING_FIELD] = info.keyframe_encoding
    if info.quantized:  # version 2: what the scale tensors mean
        metadata[QUANTIZATION_FIELD] = _dumps(quantization_description(info.dtype))
    if not info.world.is_default:  # optional: a map in arbitrary units and axes omits it
        metadata[WORLD_FIELD] = _dumps(info.world.to_dict())
    if info.camera is not None:  # optional: maps saved without known intrinsics omit it
        source = info.camera_source.value if info.camera_source is not None else None
        metadata["camera"] = _dumps({**info.camera.to_dict(), "source": source})
    metadata[_DIGEST_KEY] = metadata_digest(metadata)
    return metadata


# ---------------------------------------------------------------------------------- decoding
class _Fields:
    """Typed access to metadata fields; every failure is a MapFormatError naming the field."""

    def __init__(self, metadata: Mapping[str, str], source: str) -> None:
        self.metadata = metadata
        self.source = source

    def fail(self, message: str) -> MapFormatError:
        return MapFormatError(f"{self.source}: {message}")

    def text(self, key: str) -> str:
        return self.metadata[key]

    def json(self, key: str, kind: type) -> Any:
        value = loads_strict(self.metadata[key], f"{self.source}: header field '{key}'")
        if not isinstance(value, kind):
            raise self.fail(f"header field '{key}' must be a JSON {_JSON_NAMES[kind]}")
        return value

    def integer(self, value: Any, what: str, minimum: int = 0) -> int:
        if type(value) is not int or value < minimum:
            raise self.fail(f"{what} must be an integer >= {minimum}, got {value!r}")
        return value

    def decimal(self, key: str, minimum: int = 0) -> int:
        text = self.metadata[key]
        if not (text.isascii() and text.isdigit() and len(text) <= 18):
            raise self.fail(
                f"header field '{key}' must be a non-negative integer, got {text[:40]!r}"
            )
        return self.integer(int(text), f"header field '{key}'", minimum)


def _is_finite_number(value: Any) -> bool:
    return type(value) in (int, float) and math.isfinite(value)


def _is_vector(value: Any, length: int) -> bool:
    return isinstance(value, list) and len(value) == length and all(map(_is_finite_number, value))


def loads_strict(text: str | bytes, what: str) -> Any:
    """``json.loads`` that refuses NaN/Infinity and duplicate keys; errors are MapFormatError."""

    def no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        result = dict(pairs)
        if len(result) != len(pairs):
            raise ValueError("duplicate keys")
        return result

    def no_constants(name: str) -> Any:
        raise ValueError(f"{name} is not allowed")

    try:
        text = text.decode("utf-8") if isinstance(text, bytes) else text
        return json.loads(text, object_pairs_hook=no_duplicates, parse_constant=no_constants)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, UnicodeDecodeError: ValueErrors
        raise MapFormatError(f"{what} is not valid JSON: {str(exc)[:200]}") from exc


def _check_version(fields: _Fields) -> int:
    if fields.metadata.get("format") != FORMAT_NAME:
        raise fields.fail(f"not a kvtracker map (format is {fields.metadata.get('format')!r})")
    if "format_version" not in fields.metadata:
        raise fields.fail("header lacks 'format_version'")
    version = fields.decimal("format_version")
    if version < OLDEST_READABLE_VERSION:
        raise MapVersionError(
            f"{fields.source}: map format version {version} is too old: this SDK reads versions "
            f"{OLDEST_READABLE_VERSION} to {FORMAT_VERSION}"
        )
    if version > FORMAT_VERSION:
        raise MapVersionError(
            f"{fields.source}: map format version {version} is too new: this SDK reads versions "
            f"{OLDEST_READABLE_VERSION} to {FORMAT_VERSION}; upgrade kvtracker-sdk"
        )
    return version


def _decode_backend(fields: _Fields) -> tuple[BackendInfo, int]:
    """The saving backend's description (with the cache layout) and the tokens per frame."""
    raw = fields.json("backend", dict)
    layout = fields.json("layout", dict)
    names = ("backend", "model", "family", "config_hash", "weights_fingerprint", "dtype", "device")
    if not all(isinstance(raw.get(key), str) for key in names):
        raise fields.fail(f"backend description needs string fields {list(names)}")
    block_indices, accelerations = layout.get("block_indices"), raw.get("accelerations")
    if not isinstance(block_indices, list) or not block_indices:
        raise fields.fail("layout block_indices must be a non-empty list")
    if not isinstance(accelerations, list) or not all(isinstance(a, str) for a in accelerations):
        raise fields.fail("backend accelerations must be a list of strings")
    backend = BackendInfo(
        **{key: raw[key] for key in names},
        patch_size=fields.integer(raw.get("patch_size"), "backend patch_size", 1),
        extra_tokens_per_frame=fields.integer(raw.get("extra_tokens_per_frame"), "extra tokens"),
        layout=CacheLayout(
            block_indices=tuple(fields.integer(i, "layout block index") for i in block_indices),
            num_heads=fields.integer(layout.get("num_heads"), "layout num_heads", 1),
            head_dim=fields.integer(layout.get("head_dim"), "layout head_dim", 1),
        ),
        accelerations=tuple(accelerations),
    )
    return backend, fields.integer(layout.get("tokens_per_frame"), "tokens_per_frame", 1)


def _decode_resolution(
    fields: _Fields, backend: BackendInfo, tokens_per_frame: int
) -> tuple[int, int]:
    resolution = fields.json("resolution", list)
    if len(resolution) != 2:
        raise fields.fail(f"resolution must be [H, W], got {resolution!r}")
    height, width = (fields.integer(v, "resolution", backend.patch_size) for v in resolution)
    if tokens_per_frame != backend.tokens_per_frame(height, width):
        raise fields.fail(
            f"tokens_per_frame {tokens_per_frame} does not match {height}x{width} pixels with "
            f"patch {backend.patch_size} and {backend.extra_tokens_per_frame} extra tokens"
        )
    return height, width


def _decode_ids(fields: _Fields, key: str) -> tuple[int, ...]:
    ids = tuple(fields.integer(i, f"'{key}' entry") for i in fields.json(key, list))
    if not ids or len(set(ids)) != len(ids):
        raise fields.fail(f"'{key}' must list at least one keyframe, without duplicates")
    return ids


def gauge_problem(gauge: Sim3) -> str | None:
    """Why ``gauge`` cannot be stored in a map (its rotation is not one), or None."""
    T = np.eye(4)
    T[:3, :3] = gauge.rotation
    if not check_rigid(T, atol=RIGID_ATOL):
        return f"gauge rotation is not orthonormal with determinant +1: {gauge.rotation.tolist()}"
    low, high = GAUGE_SCALE_RANGE
    if not (math.isfinite(gauge.scale) and low <= gauge.scale <= high):
        return f"gauge scale {gauge.scale!r} is outside its range [{low:g}, {high:g}]"
    translation = np.asarray(gauge.translation, dtype=np.float64)
    if not (np.all(np.isfinite(translation))
            and float(np.abs(translation).max()) <= MAX_WORLD_TRANSLATION):
        return (f"gauge translation {translation.tolist()} is outside its range "
                f"(|t| <= {MAX_WORLD_TRANSLATION:g} per axis)")
    return None


def _decode_gauge(fields: _Fields) -> Sim3:
    raw = fields.json("gauge", dict)
    rotation, translation, scale = raw.get("rotation"), raw.get("translation"), raw.get("scale")
    if not (isinstance(rotation, list) and len(rotation) == 3 and all(_is_vector(r, 3) for r in rotation)):  # fmt: skip
        raise fields.fail("gauge rotation must be 3x3 finite numbers")
    if not _is_vector(translation, 3) or not _is_finite_number(scale) or scale <= 0:
        raise fields.fail("gauge translation must be 3 finite numbers and its scale finite and > 0")
    gauge = Sim3(
        np.array(rotation, dtype=np.float64), np.array(translation, dtype=np.float64), float(scale)
    )
    if problem := gauge_problem(gauge):
        raise fields.fail(problem)
    return gauge


def _decode_mode(fields: _Fields, tracker_config: Mapping[str, Any], version: int) -> str:
    """The tracking mode: the header field of versions 1-3, the tracker config's from version 4
    (where a header field would be a second copy that could disagree)."""
    mode: Any
    if version < MODE_IN_CONFIG_VERSION:
        if _MODE_FIELD not in fields.metadata:
            raise fields.fail(f"header lacks required fields {[_MODE_FIELD]}")
        mode, where = fields.text(_MODE_FIELD), "mode"
    else:
        if _MODE_FIELD in fields.metadata:
            raise fields.fail(f"a version-{version} header keeps the mode in 'tracker_config' only")
        mode, where = tracker_config.get(_MODE_FIELD), "tracker_config mode"
        if not isinstance(mode, str):
            raise fields.fail(f"{where} must be a string, got {str(mode)[:40]!r}")
    if mode not in _MODES:
        raise fields.fail(f"{where} must be one of {sorted(_MODES)}, got {mode[:40]!r}")
    return mode


def _decode_generation(fields: _Fields) -> int:
    generation = fields.decimal("generation")
    if generation > MAX_GENERATION:
        raise fields.fail(f"generation {generation} is above the largest valid {MAX_GENERATION}")
    return generation


def _decode_string_map(fields: _Fields, key: str) -> dict[str, str]:
    value = fields.json(key, dict)
    if not all(isinstance(v, str) for v in value.values()):
        raise fields.fail(f"'{key}' values must be strings")
    return value


def _decode_camera(fields: _Fields) -> tuple[Camera | None, IntrinsicsSource | None]:
    """The optional ``camera`` field (absent in maps saved without intrinsics)."""
    if "camera" not in fields.metadata:
        return None, None
    raw = fields.json("camera", dict)
    try:
        camera = Camera.from_dict(raw)
        source = None if raw.get("source") is None else IntrinsicsSource(raw["source"])
    except (InputError, ValueError) as exc:
        raise fields.fail(f"header field 'camera' is not a valid camera: {exc}") from exc
    return camera, source


def _optional_number(fields: _Fields, raw: dict[str, Any], key: str) -> float | None:
    value = raw.get(key)
    if value is None:
        return None
    if not _is_finite_number(value) or value < 0:
        raise fields.fail(f"header field '{WORLD_FIELD}': {key} must be a number >= 0 or null")
    return float(value)


def _decode_world(fields: _Fields) -> MapWorld:
    """The optional ``world`` field (absent in maps of arbitrary scale and axes, and in maps
    saved before it was recorded)."""
    if WORLD_FIELD not in fields.metadata:
        return MapWorld()
    raw = fields.json(WORLD_FIELD, dict)
    try:
        source = ScaleSource(raw.get("scale_source"))
    except ValueError as exc:
        raise fields.fail(f"header field '{WORLD_FIELD}': unknown scale_source "
                          f"{str(raw.get('scale_source'))[:40]!r}") from exc
    aligned = raw.get("gravity_aligned")
    if not isinstance(aligned, bool):
        raise fields.fail(f"header field '{WORLD_FIELD}': gravity_aligned must be true or false")
    return MapWorld(source, _optional_number(fields, raw, "scale_uncertainty"), aligned,
                    _optional_number(fields, raw, "gravity_uncertainty_deg"))


def _decode_created(fields: _Fields) -> datetime:
    try:
        created = datetime.fromisoformat(fields.text("created_utc"))
    except ValueError as exc:
        raise fields.fail(f"created_utc is not an ISO date: {exc}") from exc
    if created.tzinfo is None:
        raise fields.fail("created_utc must carry a timezone")
    return created


def _decode_preprocessing(fields: _Fields) -> str:
    """The optional preprocessing name; absent in maps saved before it was recorded."""
    name = fields.metadata.get(PREPROCESSING_FIELD, LEGACY_PREPROCESSING)
    if not (0 < len(name) <= 64 and name.isascii() and name.isprintable()):
        raise fields.fail(f"header field '{PREPROCESSING_FIELD}' is not a name: {name[:40]!r}")
    return name


def _decode_layer_lengths(
    fields: _Fields, layout: CacheLayout, full: int, version: int
) -> tuple[int, ...] | None:
    """The per-layer token counts of a pruned map (version 2; each within 1..N*T)."""
    if LAYER_LENGTHS_FIELD not in fields.metadata:
        return None
    if version < PRUNED_FORMAT_VERSION:
        raise fields.fail(f"a pruned map needs format version >= {PRUNED_FORMAT_VERSION}")
    raw = fields.json(LAYER_LENGTHS_FIELD, list)
    if len(raw) != layout.num_layers:
        raise fields.fail(f"'{LAYER_LENGTHS_FIELD}' must list {layout.num_layers} layers")
    lengths = tuple(fields.integer(v, f"'{LAYER_LENGTHS_FIELD}' entry", 1) for v in raw)
    if max(lengths) > full:
        raise fields.fail(f"'{LAYER_LENGTHS_FIELD}' exceed the {full} tokens of the keyframes")
    return lengths


def _decode_keyframe_encoding(fields: _Fields, version: int) -> str:
    """How the keyframe arrays are stored: "full" unless the header names a compact encoding."""
    if KEYFRAME_ENCODING_FIELD not in fields.metadata:
        return FULL
    encoding = fields.text(KEYFRAME_ENCODING_FIELD)
    if encoding not in KEYFRAME_ENCODINGS or encoding == FULL:
        raise fields.fail(
            f"unsupported '{KEYFRAME_ENCODING_FIELD}' {encoding[:40]!r} "
            f"(known: {sorted(set(KEYFRAME_ENCODINGS) - {FULL})})"
        )
    if version < KEYFRAME_ENCODINGS[encoding]:
        raise fields.fail(
            f"keyframe encoding {encoding} needs format version >= {KEYFRAME_ENCODINGS[encoding]}"
        )
    return encoding


def _decode_image_codec(
    fields: _Fields, version: int, count: int, resolution: tuple[int, int]
) -> tuple[str, tuple[int, ...] | None]:
    """How the keyframe images are stored: raw unless the header names PNG (version 4), with
    one file length per keyframe, each within what the writer can produce for the resolution."""
    if IMAGE_CODEC_FIELD not in fields.metadata:
        if IMAGE_BYTES_FIELD in fields.metadata:
            raise fields.fail(f"'{IMAGE_BYTES_FIELD}' without '{IMAGE_CODEC_FIELD}'")
        return RAW, None
    codec = fields.text(IMAGE_CODEC_FIELD)
    if codec != PNG:
        raise fields.fail(f"unsupported '{IMAGE_CODEC_FIELD}' {codec[:40]!r} (known: {PNG!r})")
    if version < IMAGE_CODEC_VERSION:
        raise fields.fail(f"PNG keyframe images need format version >= {IMAGE_CODEC_VERSION}")
    if IMAGE_BYTES_FIELD not in fields.metadata:
        raise fields.fail(f"PNG keyframe images need the header field '{IMAGE_BYTES_FIELD}'")
    raw, largest = fields.json(IMAGE_BYTES_FIELD, list), max_png_bytes(*resolution)
    if len(raw) != count:
        raise fields.fail(f"'{IMAGE_BYTES_FIELD}' must list {count} lengths, one per keyframe")
    lengths = tuple(fields.integer(v, f"'{IMAGE_BYTES_FIELD}' entry", 1) for v in raw)
    if max(lengths) > largest:
        raise fields.fail(
            f"'{IMAGE_BYTES_FIELD}' declares a PNG above the {largest} bytes of a "
            f"{resolution[0]}x{resolution[1]} image"
        )
    return codec, lengths


def _decode_cache_dtype(fields: _Fields, version: int) -> str:
    """The cache dtype; a quantised one needs version 2 and the scales' description."""
    dtype = fields.text("dtype")
    if dtype not in CACHE_DTYPES:
        raise fields.fail(f"unsupported cache dtype {dtype!r} (known: {sorted(CACHE_DTYPES)})")
    if dtype not in QUANTIZED_CACHE_DTYPES:
        if QUANTIZATION_FIELD in fields.metadata:
            raise fields.fail(f"a {dtype} cache has no '{QUANTIZATION_FIELD}'")
        return dtype
    if version < QUANTIZED_CACHE_DTYPES[dtype]:
        raise fields.fail(f"cache dtype {dtype} needs format version >= {QUANTIZED_CACHE_DTYPES[dtype]}")
    if QUANTIZATION_FIELD not in fields.metadata:
        raise fields.fail(f"a quantised ({dtype}) cache needs the header field '{QUANTIZATION_FIELD}'")
    described = fields.json(QUANTIZATION_FIELD, dict)
    if described != quantization_description(dtype):
        raise fields.fail(
            f"'{QUANTIZATION_FIELD}' {described!r} is not what this SDK reads for {dtype}: "
            f"{quantization_description(dtype)}"
        )
    return dtype


def decode_metadata(metadata: Mapping[str, str], *, file_size: int, source: str) -> MapInfo:
    """Validate ``__metadata__`` and build the MapInfo: format and version first (a newer
    version may seal its header differently), then the header checksum, then every field."""
    fields = _Fields(metadata, source)
    version = _check_version(fields)
    if metadata.get(_DIGEST_KEY) != metadata_digest(metadata):
        raise MapCorruptedError(f"{source}: header checksum mismatch (the header was altered)")
    missing = [key for key in _REQUIRED if key not in metadata]
    if missing:
        raise fields.fail(f"header lacks required fields {missing}")
    backend, tokens_per_frame = _decode_backend(fields)
    dtype = _decode_cache_dtype(fields, version)
    keyframe_ids = _decode_ids(fields, "keyframe_ids")
    cache_keyframe_ids = _decode_ids(fields, "cache_keyframe_ids")
    if set(cache_keyframe_ids) != set(keyframe_ids):
        raise fields.fail("the cache's keyframe ids differ from the keyframes' ids")
    tracker_config = fields.json("tracker_config", dict)  # parsed once, here: fail typed
    camera, camera_source = _decode_camera(fields)
    layer_lengths = _decode_layer_lengths(
        fields, backend.layout, len(cache_keyframe_ids) * tokens_per_frame, version
    )
    resolution = _decode_resolution(fields, backend, tokens_per_frame)
    image_codec, image_bytes = _decode_image_codec(fields, version, len(keyframe_ids), resolution)
    return MapInfo(
        format_version=version,
        sdk_version=fields.text("sdk_version"),
        created_utc=_decode_created(fields),
        backend=backend,
        resolution=resolution,
        dtype=dtype,
        tokens_per_frame=tokens_per_frame,
        mode=_decode_mode(fields, tracker_config, version),
        tracker_config=MappingProxyType(tracker_config),
        keyframe_ids=keyframe_ids,
        cache_keyframe_ids=cache_keyframe_ids,
        generation=_decode_generation(fields),
        gauge=_decode_gauge(fields),
        user_metadata=MappingProxyType(_decode_string_map(fields, "user_metadata")),
        tensor_sha256=MappingProxyType(_decode_string_map(fields, "tensor_sha256")),
        file_size=file_size,
        preprocessing=_decode_preprocessing(fields),
        camera=camera,
        camera_source=camera_source,
        layer_lengths=layer_lengths,
        keyframe_encoding=_decode_keyframe_encoding(fields, version),
        world=_decode_world(fields),
        image_codec=image_codec,
        image_bytes=image_bytes,
    )


def parse_header(
    header: bytes, *, file_size: int, source: str
) -> tuple[MapInfo, dict[str, str], dict[str, int]]:
    """Validate a map's raw JSON header (the ``n`` bytes after the length prefix).

    Returns the MapInfo, the raw ``__metadata__`` and each tensor's first byte in the file
    (counted from the start of the file, length prefix included). Checks, in order: JSON well-formed, a
    ``__metadata__`` of strings, format and version, header checksum, fields, then the tensor
    table against the declared layout and the file's data section
    (``file_size - 8 - len(header)`` bytes). Raises the typed map errors only.
    """
    table = loads_strict(header, f"{source}: header")
    if not isinstance(table, dict):
        raise MapFormatError(f"{source}: header is not a JSON object")
    metadata = table.pop("__metadata__", None)
    if not isinstance(metadata, dict) or not all(isinstance(v, str) for v in metadata.values()):
        raise MapFormatError(
            f"{source}: not a kvtracker map (no string __metadata__ in the header)"
        )
    info = decode_metadata(metadata, file_size=file_size, source=source)
    data_size = file_size - 8 - len(header)
    schema = info.tensor_schema()
    check_tensor_table(table, schema, info.tensor_sha256, data_size, source)
    offsets = {name: 8 + len(header) + table[name]["data_offsets"][0] for name in schema}
    return info, metadata, offsets

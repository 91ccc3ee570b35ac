"""The ``.kvmap`` tensor schema: format constants, tensor names, dtypes and shapes.

Given a header's declared layout, cache dtype, keyframe count and resolution, the schema says
exactly which tensors the file must contain, with which safetensors dtype and shape. The loader
checks the file's tensor table against it — names, dtypes, shapes, and data offsets that tile the
data section with no gap, overlap or missing byte — before any tensor byte is read.

Tensors (N keyframes, T tokens per frame, H x W model resolution, L cached layers)::

    name                               dtype     shape                   content
    layers.{i}.key, layers.{i}.value   cache     [heads, N*T, head_dim]  K/V of cached layer i, keyframe-major
    layers.{i}.kept_tokens             int64     [L_i]                   pruned maps only (below)
    layers.{i}.key_scale, .value_scale F8_E5M2   [heads, N*T, 1]         quantised caches only (version 2):
                                                                         K = key * key_scale per token and head
    keyframes.image                    uint8     [N, H, W, 3]            RGB at model resolution
    keyframes.mask                     uint8     [N, H, W]               0/1 object mask (0 where absent)
    keyframes.has_mask                 uint8     [N]                     1 if the keyframe has a mask
    keyframes.T_world_cam              float64   [N, 4, 4]               camera-to-world, world frame
    keyframes.timestamp                float64   [N]                     seconds; NaN = no timestamp
    keyframes.frame_index              int64     [N]                     session frame index
    keyframes.confidence               float32   [N, H, W]               per-pixel confidence in [0, 1]
    keyframes.mean_confidence          float64   [N]                     mean confidence over the mask
    keyframes.local_points             float32   [N, H, W, 3]            camera-frame points, world scale

A pruned map (``cache/pruning.py``, version 2) has the header field ``layer_lengths`` (L_i per
cached layer): its K/V (and scales) are then [heads, L_i, ...] and ``layers.{i}.kept_tokens``
lists which of the N*T keyframe tokens layer i kept (increasing).

The gauge (raw frame of the cache -> world) and every other scalar live in the JSON header.

Versions: 1 holds dense caches (float32, bfloat16, float16, float64). 2 adds quantised caches
(dtype ``int8`` or ``float8_e4m3fn``, with the scale tensors above and the header field
``cache_quantization``); a version-1 reader would misread them. Up to version 3 the writer
picked the oldest version that held the map (a dense map was version 1).

Version 3 adds the compact keyframe payload of quantised maps (header field
``keyframe_encoding``, ``compact-xyz`` or ``compact-depth``; ``io/map_file/keyframe_codec.py``): the mask as
bits, confidences as uint16 fixed point and the local points as float16 (or DA3-style depth
plus per-column/per-row ray slopes) instead of the ``keyframes.mask``, ``.confidence`` and
``.local_points`` rows above, which a quantised map's K/V would otherwise leave at a third of its
file. A dense map keeps the full payload (its points reload bit for bit).

Version 4 stores the tracking mode once, as the tracker config's ``"mode"`` (versions 1-3 also
had a header field ``mode``), and lets a compact map store its keyframe images as PNG files
(``io/map_file/image_codec.py``), losslessly::

    keyframes.image_png                uint8     [sum of lengths]        N PNG files end to end

in place of ``keyframes.image``, with the header fields ``keyframe_image_codec`` (``png``) and
``keyframe_image_bytes`` (each file's length, in keyframe order). Every map is written as
version 4; every version back to ``OLDEST_READABLE_VERSION`` loads.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

from kvtracker_sdk.cache.keyframe_map import LEGACY_PREPROCESSING
from kvtracker_sdk.cache.kv_cache import CacheLayout
from kvtracker_sdk.errors import MapCorruptedError, MapFormatError
from kvtracker_sdk.io.map_file.keyframe_codec import FULL, compact_tensor_specs

__all__ = [
    "CACHE_DTYPES",
    "QUANTIZATION_FIELD",
    "QUANTIZED_CACHE_DTYPES",
    "SCALE_CODE",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "GAUGE_SCALE_RANGE",
    "IMAGE_BYTES_FIELD",
    "IMAGE_CODEC_FIELD",
    "IMAGE_CODEC_VERSION",
    "MAX_WORLD_TRANSLATION",
    "KEYFRAME_ENCODING_FIELD",
    "LAYER_LENGTHS_FIELD",
    "LEGACY_PREPROCESSING",
    "MAX_GENERATION",
    "MAX_HEADER_BYTES",
    "MODE_IN_CONFIG_VERSION",
    "OLDEST_READABLE_VERSION",
    "PREPROCESSING_FIELD",
    "PRUNED_FORMAT_VERSION",
    "RIGID_ATOL",
    "TensorSpec",
    "WORLD_FIELD",
    "check_tensor_table",
    "layer_kept",
    "layer_key",
    "layer_key_scale",
    "layer_value",
    "layer_value_scale",
    "tensor_schema",
]

FORMAT_NAME = "kvtracker-map"
# bump on any change an older reader would misread (2: quantised caches, 3: compact keyframes,
# 4: the mode stored once, in the tracker config; compact maps' images as PNG)
FORMAT_VERSION = 4
OLDEST_READABLE_VERSION = 1
# Header field of version-2 quantised maps: what the scale tensors mean (checked on loading).
QUANTIZATION_FIELD = "cache_quantization"
# Optional header field (no version bump: a version-1 reader ignores it): the name of the
# preprocessing that prepared the keyframe images; absent = LEGACY_PREPROCESSING.
PREPROCESSING_FIELD = "preprocessing"
# Optional header field (no version bump: older readers ignore it): the world frame's units and
# axes (kvtracker_sdk.world.MapWorld as JSON); absent = arbitrary scale, keyframe 0's axes.
WORLD_FIELD = "world"
# Header field of a pruned map (version 2): the number of tokens each cached layer kept.
LAYER_LENGTHS_FIELD = "layer_lengths"
PRUNED_FORMAT_VERSION = 2  # the oldest version that holds a pruned map
# Header field of a map whose keyframe arrays are stored compactly (version 3, keyframe_codec);
# absent = the full payload of the table above.
KEYFRAME_ENCODING_FIELD = "keyframe_encoding"
# Version 4: the tracking mode is the tracker config's "mode" (no header field "mode"), and a
# compact map's keyframe images may be PNG files (io/map_file/image_codec.py): the header then
# names the codec and lists each file's length, which fixes the image tensor's size.
MODE_IN_CONFIG_VERSION = 4
IMAGE_CODEC_VERSION = 4
IMAGE_CODEC_FIELD = "keyframe_image_codec"
IMAGE_BYTES_FIELD = "keyframe_image_bytes"
# Our headers are a few kB (checksums, ids, the tracker config); safetensors itself allows 100 MB.
# A pickle or a zip read as a header length gives a number far above this.
MAX_HEADER_BYTES = 8 * 1024 * 1024

# A map's generation counts its mapping passes. Above 2**53 - 1 a JSON reader that holds numbers
# as doubles (JavaScript, most JSON tools) cannot represent it exactly; no session gets near it,
# so a larger value is a tampered header. Saving refuses it too: the SDK never writes a map it
# would refuse to load.
MAX_GENERATION = 2**53 - 1
# Saved keyframe poses and the gauge rotation must be rigid to this tolerance (a network's float32
# rotations are orthonormal to ~1e-7; a tampered or scaled pose is far off).
RIGID_ATOL = 1e-4
# Ranges of the numbers a tracker trusts from a header (checked on saving and on loading). The
# gauge scale is a product of depth ratios between mapping passes (each near 1); world
# positions are in the first pass's units (~metres). Beyond these a map is edited or broken, and
# tracking against it would give poses that are finite but meaningless (or overflow to inf).
GAUGE_SCALE_RANGE = (1e-6, 1e6)
MAX_WORLD_TRANSLATION = 1e6

# cache dtype name (as in BackendInfo.dtype) -> (safetensors dtype code, bytes per element)
CACHE_DTYPES: dict[str, tuple[str, int]] = {
    "float32": ("F32", 4),
    "float16": ("F16", 2),
    "bfloat16": ("BF16", 2),
    "float64": ("F64", 8),  # SimulatedBackend's cache (it carries exact Sim(3) frames in its K/V)
    "int8": ("I8", 1),  # quantised (version 2): with scale tensors
    "float8_e4m3fn": ("F8_E4M3", 1),
}
# quantised cache dtype -> the smallest format version that holds it
QUANTIZED_CACHE_DTYPES: dict[str, int] = {"int8": 2, "float8_e4m3fn": 2}
SCALE_CODE = "F8_E5M2"  # safetensors code of the scale tensors (cache/quantization.py)
_ITEMSIZE = {
    "F32": 4, "F16": 2, "BF16": 2, "F64": 8, "I64": 8, "U8": 1, "I8": 1, "F8_E4M3": 1,
    "F8_E5M2": 1, "U16": 2,
}  # fmt: skip

IMAGE = "keyframes.image"
IMAGE_PNG = "keyframes.image_png"
MASK = "keyframes.mask"
HAS_MASK = "keyframes.has_mask"
T_WORLD_CAM = "keyframes.T_world_cam"
TIMESTAMP = "keyframes.timestamp"
FRAME_INDEX = "keyframes.frame_index"
CONFIDENCE = "keyframes.confidence"
MEAN_CONFIDENCE = "keyframes.mean_confidence"
LOCAL_POINTS = "keyframes.local_points"


class TensorSpec(NamedTuple):
    dtype: str  # safetensors dtype code
    shape: tuple[int, ...]

    @property
    def nbytes(self) -> int:
        count = 1
        for dim in self.shape:
            count *= dim
        return count * _ITEMSIZE[self.dtype]


def layer_key(layer: int) -> str:
    return f"layers.{layer}.key"


def layer_value(layer: int) -> str:
    return f"layers.{layer}.value"


def layer_kept(layer: int) -> str:
    return f"layers.{layer}.kept_tokens"


def layer_key_scale(layer: int) -> str:
    return f"layers.{layer}.key_scale"


def layer_value_scale(layer: int) -> str:
    return f"layers.{layer}.value_scale"


def tensor_schema(
    layout: CacheLayout,
    cache_dtype: str,
    num_keyframes: int,
    tokens_per_frame: int,
    resolution: tuple[int, int],
    layer_lengths: tuple[int, ...] | None = None,
    keyframe_encoding: str = FULL,
    image_bytes: tuple[int, ...] | None = None,
) -> dict[str, TensorSpec]:
    """Name -> spec of every tensor of a map with these properties (see the module table);
    ``layer_lengths`` for a pruned map, ``keyframe_encoding`` (a KEYFRAME_ENCODINGS key) for
    a compact keyframe payload, ``image_bytes`` (each keyframe's PNG length) for PNG images."""
    n, (h, w) = num_keyframes, resolution
    schema = {}
    for layer in range(layout.num_layers):
        length = n * tokens_per_frame if layer_lengths is None else layer_lengths[layer]
        kv = TensorSpec(CACHE_DTYPES[cache_dtype][0], (layout.num_heads, length, layout.head_dim))
        schema[layer_key(layer)] = kv
        schema[layer_value(layer)] = kv
        if layer_lengths is not None:
            schema[layer_kept(layer)] = TensorSpec("I64", (length,))
        if cache_dtype in QUANTIZED_CACHE_DTYPES:
            scale = TensorSpec(SCALE_CODE, (layout.num_heads, length, 1))
            schema[layer_key_scale(layer)] = scale
            schema[layer_value_scale(layer)] = scale
    schema.update(
        {
            IMAGE: TensorSpec("U8", (n, h, w, 3)),
            MASK: TensorSpec("U8", (n, h, w)),
            HAS_MASK: TensorSpec("U8", (n,)),
            T_WORLD_CAM: TensorSpec("F64", (n, 4, 4)),
            TIMESTAMP: TensorSpec("F64", (n,)),
            FRAME_INDEX: TensorSpec("I64", (n,)),
            CONFIDENCE: TensorSpec("F32", (n, h, w)),
            MEAN_CONFIDENCE: TensorSpec("F64", (n,)),
            LOCAL_POINTS: TensorSpec("F32", (n, h, w, 3)),
        }
    )
    if keyframe_encoding != FULL:
        for name in (MASK, CONFIDENCE, LOCAL_POINTS):
            del schema[name]
        for name, (code, shape) in compact_tensor_specs(keyframe_encoding, n, (h, w)).items():
            schema[name] = TensorSpec(code, shape)
    if image_bytes is not None:
        del schema[IMAGE]
        schema[IMAGE_PNG] = TensorSpec("U8", (sum(image_bytes),))
    return schema


def _is_int_list(value: Any, length: int | None = None) -> bool:
    return (
        isinstance(value, list)
        and (length is None or len(value) == length)
        and all(type(v) is int and v >= 0 for v in value)
    )


def _is_sha256_hex(text: str) -> bool:
    return len(text) == 64 and all(c in "0123456789abcdef" for c in text)


def check_tensor_table(
    entries: dict[str, Any],
    schema: dict[str, TensorSpec],
    checksums: Mapping[str, str],
    data_size: int,
    source: str,
) -> None:
    """Check a header's tensor table and checksums against ``schema`` and the data section size.

    Malformed or inconsistent entries raise MapFormatError; a data section shorter or longer
    than the table declares (a truncated or padded file) raises MapCorruptedError.
    """
    missing = sorted(set(schema) - set(entries))
    unexpected = sorted(set(entries) - set(schema))
    if missing or unexpected:
        raise MapFormatError(
            f"{source}: tensor table does not match the declared layout "
            f"(missing {missing[:4]}, unexpected {unexpected[:4]})"
        )
    if set(checksums) != set(schema) or not all(map(_is_sha256_hex, checksums.values())):
        raise MapFormatError(f"{source}: tensor checksums do not cover exactly the map's tensors")
    spans = []
    for name, spec in schema.items():
        entry = entries[name]
        if not isinstance(entry, dict) or set(entry) != {"dtype", "shape", "data_offsets"}:
            raise MapFormatError(f"{source}: tensor '{name}' has a malformed table entry")
        shape, offsets = entry["shape"], entry["data_offsets"]
        if entry["dtype"] != spec.dtype or not _is_int_list(shape) or tuple(shape) != spec.shape:
            raise MapFormatError(
                f"{source}: tensor '{name}' is {entry['dtype']!r} {shape!r}, the header's layout "
                f"requires {spec.dtype} {list(spec.shape)}"
            )
        if not _is_int_list(offsets, 2) or offsets[1] - offsets[0] != spec.nbytes:
            raise MapFormatError(f"{source}: tensor '{name}' has bad data offsets {offsets!r}")
        spans.append((offsets[0], offsets[1], name))
    position = 0
    for begin, end, name in sorted(spans):
        if begin != position:
            raise MapFormatError(f"{source}: tensor data of '{name}' overlaps or leaves a gap")
        position = end
    if position > data_size:
        raise MapCorruptedError(
            f"{source} is truncated: the header declares {position} bytes of tensor data, "
            f"the file holds {data_size}"
        )
    if position < data_size:
        raise MapCorruptedError(
            f"{source} has {data_size - position} unexpected bytes after its data"
        )

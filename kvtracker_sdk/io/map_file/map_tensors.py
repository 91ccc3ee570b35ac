"""A :class:`KeyframeMap` as the map file's tensors and back, and the tensors' checksums.

The tensor names, dtypes and shapes are those of ``map_schema`` (one stacked tensor per keyframe
attribute, one K and one V tensor per cached layer). Saving snapshots the cache under its lock
into contiguous CPU tensors. Loading (``map_reader`` reads the file) rebuilds the keyframes
from their tensors, each keyframe with its own copy of its arrays, around the K/V cache that the
reader filled in place (``map_from_parts``); ``map_from_tensors`` does the same from K/V
tensors, copying them once into a new cache.
"""

from __future__ import annotations

import hashlib
import math
import os
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from kvtracker_sdk.cache.keyframe_map import Keyframe, KeyframeMap
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.errors import CacheError, MapCorruptedError, MapFormatError
from kvtracker_sdk.geometry.se3 import check_rigid
from kvtracker_sdk.io.map_file.image_codec import RAW, decode_images, encode_images
from kvtracker_sdk.io.map_file.keyframe_codec import FULL, decode_compact, encode_compact
from kvtracker_sdk.io.map_file.map_format import MapInfo
from kvtracker_sdk.io.map_file.map_schema import (
    CONFIDENCE,
    FRAME_INDEX,
    HAS_MASK,
    IMAGE,
    IMAGE_PNG,
    LOCAL_POINTS,
    MASK,
    MAX_WORLD_TRANSLATION,
    MEAN_CONFIDENCE,
    RIGID_ATOL,
    T_WORLD_CAM,
    TIMESTAMP,
    layer_kept,
    layer_key,
    layer_key_scale,
    layer_value,
    layer_value_scale,
)
from kvtracker_sdk.io.map_file.safetensors_writer import byte_pieces

__all__ = [
    "cache_problem",
    "check_digests",
    "empty_cache",
    "keyframe_problem",
    "layer_tensor_names",
    "map_from_parts",
    "map_from_tensors",
    "map_to_tensors",
    "sha256_of",
    "verify_checksums",
]

# hashlib releases the GIL on large buffers, so tensors hash in parallel; 4 threads saturate
# memory bandwidth on common machines.
_HASH_WORKERS = max(1, min(4, os.cpu_count() or 1))


def sha256_of(tensors: Mapping[str, torch.Tensor]) -> dict[str, str]:
    """Hex sha256 of each CPU tensor's bytes in row-major order (the tensors contiguous, or
    contiguous row by row, as ``write_safetensors`` takes them: hashed without a copy)."""

    def digest(tensor: torch.Tensor) -> str:
        hasher = hashlib.sha256()
        for piece in byte_pieces(tensor):
            hasher.update(piece)
        return hasher.hexdigest()

    with ThreadPoolExecutor(max_workers=_HASH_WORKERS) as pool:
        return dict(zip(tensors, pool.map(digest, tensors.values()), strict=True))


def check_digests(actual: Mapping[str, str], expected: Mapping[str, str], source: str) -> None:
    """Raise MapCorruptedError naming every tensor whose digest differs from ``expected``."""
    bad = sorted(name for name, digest in expected.items() if actual.get(name) != digest)
    if bad:
        raise MapCorruptedError(f"{source}: checksum mismatch in {len(bad)} tensor(s): {bad[:6]}")


def verify_checksums(
    tensors: Mapping[str, torch.Tensor], expected: Mapping[str, str], source: str
) -> None:
    """Raise MapCorruptedError naming every tensor whose bytes do not match ``expected``."""
    check_digests(sha256_of(tensors), expected, source)


# ---------------------------------------------------------------------------------- checks
def keyframe_problem(
    T_world_cam: np.ndarray, confidence_map: np.ndarray, mean_confidence: float
) -> str | None:
    """What makes a keyframe unfit for a map file (checked on saving and on loading), or None:
    a pose that is not a rigid transform, or confidences that are not finite and in [0, 1]."""
    if not check_rigid(T_world_cam, atol=RIGID_ATOL):
        return "pose T_world_cam is not a finite rigid transform"
    if float(np.abs(np.asarray(T_world_cam)[:3, 3]).max()) > MAX_WORLD_TRANSLATION:
        return f"pose translation is outside its range (|t| <= {MAX_WORLD_TRANSLATION:g} per axis)"
    confidence = np.asarray(confidence_map)
    if not (np.all(np.isfinite(confidence)) and confidence.min(initial=0.0) >= 0.0
            and confidence.max(initial=0.0) <= 1.0):  # fmt: skip
        return "confidence map is not finite and within [0, 1]"
    if not (math.isfinite(mean_confidence) and 0.0 <= mean_confidence <= 1.0):
        return f"mean confidence {mean_confidence!r} is not within [0, 1]"
    return None


# ---------------------------------------------------------------------------------- saving
def _checked(kf: Keyframe, name: str, value: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    array = np.asarray(value)
    if array.shape != shape:
        raise MapFormatError(
            f"cannot save map: keyframe {kf.keyframe_id} {name} has shape {array.shape}, expected {shape}"
        )
    return array


def _stack(
    keyframe_map: KeyframeMap, name: str, shape: tuple[int, ...], dtype: type
) -> torch.Tensor:
    arrays = [_checked(kf, name, getattr(kf, name), shape) for kf in keyframe_map.keyframes]
    return torch.from_numpy(np.stack(arrays).astype(dtype, copy=False))


def layer_tensor_names(layer: int) -> dict[str, str]:
    """``KVCache.stored_parts`` name -> map file tensor name, for cached layer ``layer``."""
    return {
        "key": layer_key(layer),
        "value": layer_value(layer),
        "key_scale": layer_key_scale(layer),
        "value_scale": layer_value_scale(layer),
    }


def _cache_layers(cache: KVCache, *, views: bool = False) -> dict[str, torch.Tensor]:
    """Contiguous CPU copies [heads, L_i, head_dim or 1] of what every layer stores at rest (a
    quantised cache: its data and scales, never a dequantised copy; L_i = N*T unless pruned, and a
    pruned cache adds each layer's kept token indices). ``views``: views of the cache's own
    buffers instead (each head contiguous), valid only while the caller holds ``cache.lock``."""
    layers = {}
    with cache.lock:  # a consistent snapshot even if another thread edits the cache afterwards
        for i in range(cache.layout.num_layers):
            names = layer_tensor_names(i)
            for part, view in cache.stored_parts(i).items():
                copy = None if views else torch.empty(view.shape[1:], dtype=view.dtype)
                layers[names[part]] = view[0] if copy is None else copy.copy_(view[0])
            if cache.pruned:
                layers[layer_kept(i)] = cache.kept_tokens(i).contiguous()
    return layers


def map_to_tensors(
    keyframe_map: KeyframeMap,
    resolution: tuple[int, int],
    *,
    compact: bool = False,
    cache_views: bool = False,
) -> tuple[dict[str, torch.Tensor], str, tuple[int, ...] | None]:
    """The map's tensors (contiguous, CPU) for a file at ``resolution`` (H, W), their keyframe
    encoding (``"full"``, or with ``compact`` the one ``keyframe_codec`` chose) and, when
    ``compact`` stores the images as PNG files (``image_codec``: when smaller), their lengths.
    ``cache_views``: the K/V as views of the cache's buffers, not copies (contiguous head by
    head; the caller holds ``keyframe_map.cache.lock`` for as long as it uses them).

    Raises MapFormatError if a keyframe's arrays do not match the resolution or a pose is not
    finite: such a map could not be loaded back.
    """
    h, w = resolution
    kfs = keyframe_map.keyframes
    for kf in kfs:
        if np.asarray(kf.image).dtype != np.uint8:
            raise MapFormatError(f"cannot save map: keyframe {kf.keyframe_id} image is not uint8")
        problem = keyframe_problem(kf.T_world_cam, kf.confidence_map, kf.mean_confidence)
        if problem:  # the loader's checks: the SDK never writes a map it would refuse
            raise MapFormatError(f"cannot save map: keyframe {kf.keyframe_id} {problem}")
    masks = np.stack([
        np.zeros((h, w), bool) if kf.mask is None else _checked(kf, "mask", kf.mask, (h, w)) != 0
        for kf in kfs
    ])  # fmt: skip
    confidence = _stack(keyframe_map, "confidence_map", (h, w), np.float32)
    points = _stack(keyframe_map, "local_points", (h, w, 3), np.float32)
    images = _stack(keyframe_map, "image", (h, w, 3), np.uint8)
    pngs = encode_images(images.numpy()) if compact else None
    image_bytes = None if pngs is None else pngs[1]
    if compact:
        encoding, payload = encode_compact(masks, confidence.numpy(), points.numpy())
    else:
        encoding = FULL
        payload = {
            MASK: torch.from_numpy(masks.astype(np.uint8)),
            CONFIDENCE: confidence,
            LOCAL_POINTS: points,
        }
    tensors = {
        **_cache_layers(keyframe_map.cache, views=cache_views),
        **({IMAGE: images} if pngs is None else {IMAGE_PNG: torch.from_numpy(pngs[0])}),
        HAS_MASK: torch.tensor([kf.mask is not None for kf in kfs], dtype=torch.uint8),
        T_WORLD_CAM: _stack(keyframe_map, "T_world_cam", (4, 4), np.float64),
        TIMESTAMP: torch.tensor(
            [math.nan if kf.timestamp is None else kf.timestamp for kf in kfs], dtype=torch.float64
        ),
        FRAME_INDEX: torch.tensor([kf.frame_index for kf in kfs], dtype=torch.int64),
        MEAN_CONFIDENCE: torch.tensor([kf.mean_confidence for kf in kfs], dtype=torch.float64),
        **payload,
    }
    return tensors, encoding, image_bytes


# ---------------------------------------------------------------------------------- loading
def _keyframes(
    tensors: Mapping[str, torch.Tensor], info: MapInfo, source: str
) -> tuple[Keyframe, ...]:
    """Keyframes with their own copies of the arrays (never views of the file mapping)."""
    poses = tensors[T_WORLD_CAM].numpy()
    has_mask = tensors[HAS_MASK].numpy()
    if not np.all((has_mask == 0) | (has_mask == 1)):
        raise MapCorruptedError(f"{source}: mask presence flags must be 0 or 1")
    if info.image_codec == RAW:
        images = tensors[IMAGE].numpy()
    else:  # decoded into a new array: the per-keyframe copies below are the only others
        images = decode_images(
            tensors[IMAGE_PNG].numpy(), info.image_bytes or (), info.resolution, source
        )
    if info.keyframe_encoding == FULL:
        masks = tensors[MASK].numpy() != 0
        confidence, points = tensors[CONFIDENCE].numpy(), tensors[LOCAL_POINTS].numpy()
    else:  # decoded into new arrays: the per-keyframe copies below are the only others
        masks, confidence, points = decode_compact(
            tensors, info.keyframe_encoding, info.resolution, source
        )
    stamps, frames = tensors[TIMESTAMP].numpy(), tensors[FRAME_INDEX].numpy()
    mean_confidence = tensors[MEAN_CONFIDENCE].numpy()
    for i, keyframe_id in enumerate(info.keyframe_ids):  # the same checks as on saving
        problem = keyframe_problem(poses[i], confidence[i], float(mean_confidence[i]))
        if problem:
            raise MapCorruptedError(f"{source}: keyframe {keyframe_id} {problem}")
    return tuple(
        Keyframe(
            keyframe_id=keyframe_id,
            frame_index=int(frames[i]),
            timestamp=None if math.isnan(stamps[i]) else float(stamps[i]),
            image=images[i].copy(),
            mask=masks[i].copy() if has_mask[i] else None,
            T_world_cam=poses[i].copy(),
            confidence_map=confidence[i].copy(),
            local_points=points[i].copy(),
            mean_confidence=float(mean_confidence[i]),
        )
        for i, keyframe_id in enumerate(info.keyframe_ids)
    )


def stored_compute_dtype(info: MapInfo) -> torch.dtype:
    """The compute dtype of a loaded map's cache before any backend asks for its own: a dense
    cache's stored dtype; for a quantised one the saving backend's dtype (float32 if that is not
    a float dtype torch knows)."""
    if not info.quantized:
        return getattr(torch, info.dtype)
    name = info.backend.dtype
    dtype = getattr(torch, name, None) if name in ("float32", "bfloat16", "float16") else None
    return dtype if isinstance(dtype, torch.dtype) else torch.float32


def map_from_tensors(
    tensors: Mapping[str, torch.Tensor],
    info: MapInfo,
    source: str,
    *,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> KeyframeMap:
    """Rebuild the KeyframeMap from a file's (validated, verified) tensors.

    The K/V are copied once into the cache's preallocated buffers; with ``dtype``/``device``
    the cache is then converted (one more copy, only when they differ from the file's).
    """
    try:
        cache = empty_cache(
            info,
            None
            if info.layer_lengths is None
            else [tensors[layer_kept(i)] for i in range(info.layout.num_layers)],
        )
        for layer in range(info.layout.num_layers):
            names = layer_tensor_names(layer)
            for part, view in cache.stored_parts(layer).items():
                view[0].copy_(tensors[names[part]])
    except (CacheError, RuntimeError) as exc:  # the schema check makes this unreachable
        raise MapCorruptedError(f"{source}: the K/V tensors do not form a cache: {exc}") from exc
    return map_from_parts(tensors, cache, info, source, dtype=dtype, device=device)


def empty_cache(info: MapInfo, kept_tokens: list[torch.Tensor] | None) -> KVCache:
    """The preallocated CPU cache a map file's K/V are copied into: the file's storage and
    compute dtype, and per layer the kept token indices of a pruned map (None: not pruned);
    ``CacheError`` when those indices are invalid."""
    return KVCache.preallocated(
        info.layout,
        info.tokens_per_frame,
        info.cache_keyframe_ids,
        dtype=stored_compute_dtype(info),
        storage=info.dtype,
        kept_tokens=kept_tokens,
    )


# per float dtype: the integer type of its width and the mask of its exponent bits; a value is
# NaN or infinite exactly when all of them are set
_EXPONENT_BITS: dict[torch.dtype, tuple[type, int]] = {
    torch.bfloat16: (np.int16, 0x7F80),
    torch.float16: (np.int16, 0x7C00),
    torch.float32: (np.int32, 0x7F800000),
    torch.float64: (np.int64, 0x7FF0000000000000),
}


def _all_finite(tensor: torch.Tensor) -> bool:
    """Whether every value of ``tensor`` (a float dtype; [1, H, L, X] as ``stored_parts`` gives
    it, each head contiguous) is finite.

    Read head by head from the buffers as integers, with numpy: ``isfinite(tensor.float())``
    converts the whole K/V to float32 first, and torch's own reductions split over its OpenMP
    threads, which stall on a busy machine; either is slower than the load's own read. float8
    has neither a numpy type nor a torch ``max``: it is converted (one byte per value).
    """
    bits = _EXPONENT_BITS.get(tensor.dtype)
    if bits is None:
        return bool(torch.isfinite(tensor.float()).all())
    integer, mask = bits
    heads = tensor[0] if tensor.dim() > 1 else tensor
    try:
        pieces = byte_pieces(heads)
    except ValueError:  # not a layout the cache hands out: check a contiguous copy
        pieces = byte_pieces(heads.contiguous())
    return all(
        int(np.bitwise_and(np.frombuffer(piece, dtype=integer), mask).max(initial=0)) != mask
        for piece in pieces
    )


def cache_problem(cache: KVCache) -> str | None:
    """What makes a loaded cache's stored values impossible, or None.

    A quantised cache's scales must be finite and within what ``quantization.round_up`` can
    produce (the scale dtype's smallest normal to its largest value): a zero, negative,
    subnormal or NaN scale gives K/V that are wrong but finite, and poses marked valid that are
    off by metres. Its int8 data lie in [-127, 127] (the quantiser clamps there) and its fp8
    data are finite; a dense cache's K/V must be finite."""
    for layer in range(cache.layout.num_layers):
        parts = cache.stored_parts(layer)
        for name, tensor in parts.items():
            if name.endswith("_scale"):
                info = torch.finfo(tensor.dtype)
                values = tensor.float()
                if values.numel() and not bool(
                    (torch.isfinite(values) & (values >= info.tiny) & (values <= info.max)).all()
                ):
                    return (f"layer {layer} {name}: a scale outside [{info.tiny:g}, {info.max:g}] "
                            "(zero, negative, subnormal or not finite)")
            elif tensor.dtype == torch.int8:
                if tensor.numel() and int(tensor.min()) < -127:
                    return f"layer {layer} {name}: int8 data outside [-127, 127]"
            elif tensor.numel() and not _all_finite(tensor):
                return f"layer {layer} {name}: values that are not finite"
    return None


def map_from_parts(
    tensors: Mapping[str, torch.Tensor],
    cache: KVCache,
    info: MapInfo,
    source: str,
    *,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> KeyframeMap:
    """Rebuild the KeyframeMap from a file's keyframe tensors and its K/V already in ``cache``
    (converted to ``dtype``/``device`` when they differ from the file's)."""
    keyframes = _keyframes(tensors, info, source)
    if problem := cache_problem(cache):
        raise MapCorruptedError(f"{source}: {problem}")
    if (dtype is not None and dtype != cache.dtype) or (
        device is not None and torch.device(device) != cache.device
    ):
        cache = cache.to(dtype=dtype, device=device)
    return KeyframeMap(
        keyframes=keyframes,
        cache=cache,
        gauge=info.gauge,
        generation=info.generation,
        resolution=info.resolution,
        metadata=dict(info.user_metadata),
        preprocessing=info.preprocessing,
        world=info.world,
    )

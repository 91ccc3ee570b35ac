"""Small synthetic maps for the map-file tests (no model): random K/V, images, poses.

Also used by child processes (round-trip and crash tests), so everything is seeded and built
from plain arguments. ``rewrite_header`` edits a saved file's JSON header, re-sealing the
metadata checksum by default, to build files that are valid except for one chosen field.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import torch

from kvtracker_sdk.backends.base import BackendInfo
from kvtracker_sdk.cache import CacheLayout, Keyframe, KeyframeMap, KVCache
from kvtracker_sdk.geometry.se3 import rotation_from_quat_xyzw
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.io.map_file.map_format import metadata_digest

PATCH = 14
EXTRA_TOKENS = 5
TRACKER_CONFIG = '{"mode": "object", "keyframing": {"view_angle_deg": 10.0}}'


def backend_info(
    *,
    layers: int = 4,
    heads: int = 2,
    head_dim: int = 8,
    dtype: str = "float32",
    **overrides: Any,
) -> BackendInfo:
    """A BackendInfo for the synthetic model; ``overrides`` replace any other field."""
    fields: dict[str, Any] = {
        "backend": "torch",
        "model": "pi3-test",
        "family": "pi3",
        "config_hash": "cfg0123456789abc",
        "weights_fingerprint": "w0123456789abcde",
        "patch_size": PATCH,
        "extra_tokens_per_frame": EXTRA_TOKENS,
        "layout": CacheLayout(tuple(range(1, 2 * layers, 2)), heads, head_dim),
        "dtype": dtype,
    }
    fields.update(overrides)
    return BackendInfo(**fields)


def _pose(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotation_from_quat_xyzw(rng.normal(size=4))
    T[:3, 3] = rng.normal(size=3)
    return T


def make_map(
    *,
    num_keyframes: int = 3,
    layers: int = 4,
    heads: int = 2,
    head_dim: int = 8,
    size: tuple[int, int] = (28, 42),
    dtype: torch.dtype = torch.float32,
    seed: int = 0,
    generation: int = 2,
    storage: str | None = None,
) -> KeyframeMap:
    """A map with random content; keyframe 1 has no mask and no timestamp (both optional);
    ``storage`` ``"int8"`` / ``"float8_e4m3fn"`` quantises its cache."""
    rng = np.random.default_rng(seed)
    h, w = size
    tokens = EXTRA_TOKENS + (h // PATCH) * (w // PATCH)
    layout = CacheLayout(tuple(range(1, 2 * layers, 2)), heads, head_dim)
    generator = torch.Generator().manual_seed(seed)
    shape = (1, heads, num_keyframes * tokens, head_dim)
    keys = [torch.randn(shape, generator=generator).to(dtype) for _ in range(layers)]
    values = [torch.randn(shape, generator=generator).to(dtype) for _ in range(layers)]
    ids = [3 * i + 1 for i in range(num_keyframes)]  # not 0..N-1: ids must survive as given
    cache = KVCache.from_layers(
        keys, values, layout=layout, tokens_per_frame=tokens, keyframe_ids=ids, storage=storage
    )
    keyframes = tuple(
        Keyframe(
            keyframe_id=kf_id,
            frame_index=10 * i,
            timestamp=None if i == 1 else 1311868164.363181 + 0.5 * i,
            image=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
            mask=None if i == 1 else rng.random((h, w)) > 0.5,
            T_world_cam=np.eye(4) if i == 0 else _pose(rng),
            confidence_map=rng.random((h, w), dtype=np.float32),
            local_points=(rng.normal(size=(h, w, 3)) + [0.0, 0.0, 2.0]).astype(np.float32),
            mean_confidence=float(rng.random()),
        )
        for i, kf_id in enumerate(ids)
    )
    gauge = Sim3(
        rotation_from_quat_xyzw(rng.normal(size=4)), rng.normal(size=3), 0.1 + rng.random()
    )
    return KeyframeMap(
        keyframes=keyframes,
        cache=cache,
        gauge=gauge,
        generation=generation,
        resolution=(h, w),
        metadata={"scene": "desk"},
    )


def split_file(data: bytes) -> tuple[dict[str, Any], bytes]:
    """(JSON header, tensor data) of a safetensors file's bytes."""
    size = int.from_bytes(data[:8], "little")
    return json.loads(data[8 : 8 + size]), data[8 + size :]


def join_file(header: dict[str, Any], body: bytes) -> bytes:
    raw = json.dumps(header).encode()
    return len(raw).to_bytes(8, "little") + raw + body


def rewrite_header(
    data: bytes, edit: Callable[[dict[str, Any]], None], *, reseal: bool = True
) -> bytes:
    """Apply ``edit`` to the file's JSON header; re-seal the metadata checksum unless told not to."""
    header, body = split_file(data)
    edit(header)
    metadata = header.get("__metadata__")
    if reseal and isinstance(metadata, dict) and "metadata_sha256" in metadata:
        metadata["metadata_sha256"] = metadata_digest(metadata)
    return join_file(header, body)


def maps_equal(a: KeyframeMap, b: KeyframeMap) -> bool:
    """Bit-identical cache, keyframes (all arrays, ids, stamps), gauge, generation, metadata."""
    if not a.cache.equals(b.cache) or a.keyframe_ids != b.keyframe_ids:
        return False
    for x, y in zip(a.keyframes, b.keyframes, strict=True):
        if (x.frame_index, x.timestamp, x.mean_confidence) != (
            y.frame_index,
            y.timestamp,
            y.mean_confidence,
        ):
            return False
        if (x.mask is None) != (y.mask is None) or (
            x.mask is not None and not np.array_equal(x.mask, y.mask)
        ):
            return False
        for name in ("image", "T_world_cam", "confidence_map", "local_points"):
            u, v = getattr(x, name), getattr(y, name)
            if u.dtype != v.dtype or not np.array_equal(u, v):
                return False
    return (
        np.array_equal(a.gauge.matrix(), b.gauge.matrix())
        and a.gauge.scale == b.gauge.scale
        and (a.generation, a.resolution, a.metadata) == (b.generation, b.resolution, b.metadata)
    )


# what a compact keyframe payload (io/map_file/keyframe_codec.py) may change: confidences by half a
# uint16 step (+ float32 rounding), points by float16's relative rounding 2**-11 (+ float32's
# rounding of a depth x ray product, well below 1e-6)
CONFIDENCE_ATOL = 0.5 / 65535 + 1e-7
POINTS_RTOL = 2.0**-11 + 1e-6


def compact_maps_match(a: KeyframeMap, b: KeyframeMap) -> bool:
    """Like ``maps_equal``, but confidences and points within the compact payload's bounds."""
    def exact(kf: Any) -> Any:
        return replace(kf, confidence_map=np.zeros(1), local_points=np.zeros(1))

    if not maps_equal(
        replace(a, keyframes=tuple(map(exact, a.keyframes))),
        replace(b, keyframes=tuple(map(exact, b.keyframes))),
    ):
        return False
    for x, y in zip(a.keyframes, b.keyframes, strict=True):
        u, v = x.confidence_map, y.confidence_map
        if u.dtype != v.dtype or np.abs(u - v).max() > CONFIDENCE_ATOL:
            return False
        p, q = x.local_points, y.local_points
        if p.dtype != q.dtype or np.any(np.abs(p - q) > POINTS_RTOL * np.abs(q)):
            return False
    return True


def _sha(array: np.ndarray | torch.Tensor) -> str:
    if isinstance(array, torch.Tensor):
        array = array.contiguous().reshape(-1).view(torch.uint8).numpy()
    return (
        f"{array.dtype}{list(array.shape)}:"
        + hashlib.sha256(np.ascontiguousarray(array)).hexdigest()
    )


def map_digest(keyframe_map: KeyframeMap) -> dict[str, Any]:
    """Everything in a map reduced to JSON (hashes of array bytes, exact reprs of scalars), to
    compare maps held by different processes bit for bit."""
    cache = keyframe_map.cache
    digest: dict[str, Any] = {
        "cache": [str(cache.dtype), list(cache.keyframe_ids), cache.tokens_per_frame],
        "gauge": [keyframe_map.gauge.rotation.tolist(), keyframe_map.gauge.translation.tolist(),
                  keyframe_map.gauge.scale],
        "map": [keyframe_map.generation, list(keyframe_map.resolution), keyframe_map.metadata],
    }  # fmt: skip
    for i in range(cache.layout.num_layers):
        digest[f"k{i}"] = _sha(cache.keys(i))
        digest[f"v{i}"] = _sha(cache.values(i))
    for kf in keyframe_map.keyframes:
        arrays = [kf.image, kf.T_world_cam, kf.confidence_map, kf.local_points]
        digest[f"kf{kf.keyframe_id}"] = [
            kf.frame_index,
            repr(kf.timestamp),
            repr(kf.mean_confidence),
            None if kf.mask is None else _sha(kf.mask),
            *map(_sha, arrays),
        ]
    return digest

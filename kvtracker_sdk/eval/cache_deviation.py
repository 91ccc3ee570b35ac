"""Accuracy proxy for compact caches: how far tracking moves from the full-precision fp32 cache.

Real weights are not reachable everywhere, so the cost of compressing or pruning a cache is
measured as a *deviation*: map a few keyframes, track the other frames against the cache, and
compare each tracked pose and point map with those of the same frames tracked by the fp32 model
against its uncompressed fp32 cache. The same numbers for the bf16 backend (bf16 matrix products
and a bf16 cache: a perturbation users already accept) are the yardstick. On random or reduced
weights this says how much a variant perturbs the network's function, not how accurate it is on
real scenes: the accuracy cost on real weights stays unmeasured until someone runs this with them.

A :class:`CacheVariant` names the backend dtype of both passes, an optional cache storage
(``"int8"``, ``"fp8"``, ...) and an optional ``transform`` of the cache made by the mapping pass
(e.g. a pruning budget), so other compressions plug in without changing this module::

    frames = tum_frames(TumSource(path), backend.info.family, resolution=224)
    rows = cache_deviation(weights, frames, keyframes=[0, 5, 10, 15],
                           variants=[CacheVariant("bf16", dtype="bfloat16"),
                                     CacheVariant("int8", storage="int8")])

Metrics per variant, over the tracked frames: ``pose_max`` / ``pose_median`` — the largest
absolute entry of ``T - T_ref`` over the rotation and translation rows of each frame (the
measure of the golden bf16 tests), then the max / median over frames; ``rotation_deg_max``;
``points_median`` — the median over pixels and frames of |p - p_ref| / |p_ref| of the
camera-frame points; ``cache_bytes`` (at rest).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.preprocess.families import for_family
from kvtracker_sdk.types import HeadSet

__all__ = ["CacheVariant", "Deviation", "cache_deviation", "tracked_outputs", "tum_frames"]


@dataclass(frozen=True)
class CacheVariant:
    """One way of making the cache that tracking reads."""

    name: str
    dtype: str = "float32"  # the backend's dtype for the mapping and tracking passes
    storage: str | None = None  # cache storage (None: dense in ``dtype``)
    transform: Callable[[KVCache], KVCache] | None = None  # applied after ``storage``


@dataclass(frozen=True)
class Deviation:
    """A variant's tracking against the reference (see the module docstring)."""

    variant: str
    cache_bytes: int
    pose_max: float
    pose_median: float
    rotation_deg_max: float
    points_median: float

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def tum_frames(frames: Iterable[Any], family: str, *, resolution: int) -> np.ndarray:
    """uint8 [F, h, w, 3] model inputs of ``frames`` (``SourceFrame``-like: ``.image``),
    prepared by ``family``'s preprocessing at ``resolution`` as the tracker prepares them."""
    preprocessing = for_family(family)
    return np.stack([preprocessing.resize(f.image, resolution, 14).image for f in frames])


def _cache(backend: TorchBackend, images: np.ndarray, variant: CacheVariant) -> KVCache:
    cache = backend.map(images).cache
    if variant.storage is not None:
        cache = cache.to(storage=variant.storage)
    return variant.transform(cache) if variant.transform is not None else cache


def tracked_outputs(
    backend: TorchBackend, frames: np.ndarray, keyframes: Sequence[int], variant: CacheVariant
) -> tuple[np.ndarray, np.ndarray, int]:
    """Map ``frames[keyframes]``, track every other frame (one pass, all heads): poses
    [Q, 4, 4], local points [Q, h, w, 3] and the cache's bytes at rest."""
    cache = _cache(backend, frames[list(keyframes)], variant)
    queries = [i for i in range(len(frames)) if i not in set(keyframes)]
    results = backend.track_batch(frames[queries], cache, heads=HeadSet.ALL)
    points = [r.local_points for r in results]
    if any(p is None for p in points):  # HeadSet.ALL always decodes points
        raise ValueError("the backend returned no local points")
    return np.stack([r.pose for r in results]), np.stack(points), cache.nbytes  # type: ignore[arg-type]


def _rotation_deg(rotation: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Angle between rotations [Q, 3, 3] per frame, degrees: 2 asin(|R - R_ref|_F / sqrt 8),
    which (unlike acos of the trace) is exact near zero."""
    chord = np.linalg.norm(rotation - reference, axis=(1, 2)) / np.sqrt(8.0)
    return np.degrees(2.0 * np.arcsin(np.clip(chord, 0.0, 1.0)))


def compare(
    name: str, outputs: tuple[np.ndarray, np.ndarray, int], reference: tuple[np.ndarray, np.ndarray]
) -> Deviation:
    """The deviation of ``outputs`` (poses, points, bytes) from ``reference`` (poses, points)."""
    poses, points, nbytes = outputs
    ref_poses, ref_points = reference
    per_frame = np.abs(poses - ref_poses)[:, :3, :].max(axis=(1, 2))
    norm = np.maximum(np.linalg.norm(ref_points, axis=-1), 1e-12)
    relative = np.linalg.norm(points - ref_points, axis=-1) / norm
    rotation = _rotation_deg(poses[:, :3, :3], ref_poses[:, :3, :3])
    return Deviation(
        variant=name,
        cache_bytes=int(nbytes),
        pose_max=float(per_frame.max()),
        pose_median=float(np.median(per_frame)),
        rotation_deg_max=float(rotation.max()),
        points_median=float(np.median(relative)),
    )


def cache_deviation(
    weights: str | os.PathLike[str],
    frames: np.ndarray,
    keyframes: Sequence[int],
    variants: Sequence[CacheVariant],
) -> list[Deviation]:
    """Deviation of each variant from the fp32 model on its fp32 cache (first row: that
    reference itself, all zeros), ``frames`` uint8 [F, h, w, 3] at model size."""
    backends: dict[str, TorchBackend] = {}

    def backend(dtype: str) -> TorchBackend:
        if dtype not in backends:
            backends[dtype] = TorchBackend.from_pretrained(weights, dtype=dtype)
        return backends[dtype]

    reference_variant = CacheVariant("fp32")
    poses, points, nbytes = tracked_outputs(backend("float32"), frames, keyframes, reference_variant)
    rows = [compare("fp32", (poses, points, nbytes), (poses, points))]
    for variant in variants:
        outputs = tracked_outputs(backend(variant.dtype), frames, keyframes, variant)
        rows.append(compare(variant.name, outputs, (poses, points)))
    return rows

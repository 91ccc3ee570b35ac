"""Checks every backend makes on its inputs, with the SDK's typed errors.

Frames arrive at the model resolution as uint8 RGB [N, H, W, 3] (``backends/base.py``; float32
RGB in [0, 1] is accepted too, so research code can feed exact float inputs); masks
are bool [N, H, W]; a cache must have the backend's layout, dtype, device and tokens per frame.
A failed check raises before anything runs, so the caller's cache and map are untouched.
"""

from __future__ import annotations

import numpy as np

from kvtracker_sdk.backends.base import BackendInfo
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.errors import (
    BackendMismatchError,
    ImageDtypeError,
    ImageShapeError,
    MaskError,
    ResolutionChangedError,
)

__all__ = [
    "QUANTIZED_CACHE_BACKENDS",
    "check_cache",
    "check_frames",
    "check_masks",
    "check_uniform_lengths",
    "reads_quantized_caches",
]


def check_frames(images: object, patch_size: int) -> np.ndarray:
    """``images`` as a uint8 (or float32 in [0, 1]) [N, H, W, 3] array with N >= 1 and H, W
    multiples of ``patch_size``."""
    if not isinstance(images, np.ndarray):
        raise ImageDtypeError(f"images must be a numpy uint8 array, got {type(images).__name__}")
    if images.ndim != 4 or images.shape[-1] != 3 or images.shape[0] == 0:
        raise ImageShapeError(f"expected images [N, H, W, 3] with N >= 1, got shape {images.shape}")
    if images.dtype == np.float32:  # research use (golden checks): float RGB in [0, 1]
        if not (np.isfinite(images).all() and images.min() >= 0.0 and images.max() <= 1.0):
            raise ImageDtypeError("float32 images must be finite RGB values in [0, 1]")
    elif images.dtype != np.uint8:
        raise ImageDtypeError(f"images must be uint8 RGB (or float32 in [0, 1]), got {images.dtype}")
    height, width = images.shape[1:3]
    if height % patch_size or width % patch_size or height < patch_size or width < patch_size:
        raise ImageShapeError(
            f"image size {height}x{width} is not a positive multiple of {patch_size}: resize it "
            "with kvtracker_sdk.preprocess.for_family(family).resize first"
        )
    return images


def check_masks(masks: np.ndarray | None, images: np.ndarray) -> None:
    """``masks`` None or bool [N, H, W] matching ``images`` [N, H, W, 3]."""
    if masks is not None and (
        not isinstance(masks, np.ndarray)
        or masks.dtype != np.bool_
        or masks.shape != images.shape[:3]
    ):
        raise MaskError(
            f"masks must be bool {images.shape[:3]}, got "
            f"{getattr(masks, 'dtype', type(masks).__name__)} {getattr(masks, 'shape', '')}"
        )


# Backends whose passes read a quantised cache layer by layer (``KVCache.buffers``). ONNX graphs
# take every layer's K/V as inputs at once, which would need a full-precision copy of the whole
# cache per step; the simulated backend reads exact frames from its float64 K/V.
QUANTIZED_CACHE_BACKENDS = frozenset({"torch"})


def reads_quantized_caches(info: BackendInfo) -> bool:
    """Whether the backend described by ``info`` tracks against int8 / fp8 caches."""
    return info.backend in QUANTIZED_CACHE_BACKENDS


def check_cache(cache: KVCache, info: BackendInfo, height: int, width: int) -> None:
    """The cache fits the backend (layout, dtype, device) and frames of ``height`` x ``width``."""
    if cache.layout != info.layout:
        raise BackendMismatchError(
            f"cache layout {cache.layout} does not match this model's {info.layout}"
        )
    if cache.quantized and not reads_quantized_caches(info):
        raise BackendMismatchError(
            f"the {info.backend} backend cannot track against a quantised ({cache.storage}) cache: "
            f"convert it with cache.to(storage={info.dtype!r}) or use the PyTorch backend"
        )
    dtype = str(cache.dtype).removeprefix("torch.")
    if dtype != info.dtype or str(cache.device) != info.device:
        raise BackendMismatchError(
            f"cache is {dtype} on {cache.device}, the backend computes in {info.dtype} on "
            f"{info.device}: convert it with cache.to(dtype=..., device=...)"
        )
    expected = info.tokens_per_frame(height, width)
    if cache.tokens_per_frame != expected:
        raise ResolutionChangedError(
            f"the cache holds {cache.tokens_per_frame} tokens per keyframe but a {height}x{width} "
            f"frame has {expected}: track at the keyframes' resolution"
        )


def check_uniform_lengths(cache: KVCache) -> None:
    """An exported tracking graph takes one ``past_length`` for every layer: refuse a cache whose
    layers hold different numbers of tokens (``cache.pruning.prune_cache`` never makes one; a
    hand-pruned cache may) with ``BackendMismatchError``."""
    lengths = {cache.layer_length(i) for i in range(cache.layout.num_layers)}
    if len(lengths) > 1:
        raise BackendMismatchError(
            f"the cache's layers hold different numbers of tokens ({sorted(lengths)}); the ONNX "
            "tracking graph takes one past_length: prune every layer to the same budget"
        )

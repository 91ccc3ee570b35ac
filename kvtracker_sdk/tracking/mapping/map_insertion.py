"""Incremental keyframes: add a keyframe with one tracking pass instead of a full mapping pass.

A full rebuild re-runs the mapping pass over every keyframe, O((N·M)²), because in a global layer
each keyframe's K/V depend on all the others. An insertion runs the candidate alone against the
current map — the tracking pass, O(M²·(N+1)) — and keeps the K/V that pass writes into the
cache's scratch (``KVCache.adopt_scratch``): the candidate's tokens attended to every keyframe,
but the older keyframes never see the new one, and their K/V and poses stay as they were. That is
an approximation, so a full rebuild still runs every ``rebuild_every`` insertions, and whenever
the candidate's confidence in its insertion pass falls below ``rebuild_below`` of keyframe 0's.

The insertion works on a copy of the map's cache (the tracker keeps tracking against the
original), on backends whose tracking pass writes the scratch (PyTorch) and dense caches (a
quantised cache's pass writes one shared work pair); otherwise the map is rebuilt.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from kvtracker_sdk.backends.base import Backend
from kvtracker_sdk.cache.keyframe_map import Keyframe, KeyframeMap
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.config import MapCompactionConfig, RejectionConfig
from kvtracker_sdk.errors import BackendError
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.tracking.core.gauge import keyframe_corrections
from kvtracker_sdk.tracking.core.quality import masked_mean
from kvtracker_sdk.tracking.mapping.map_builder import (
    RebuildCause,
    RebuildOutcome,
    RebuildRequest,
    build_map,
)
from kvtracker_sdk.types import HeadSet

__all__ = ["insert_keyframe", "rebuild_or_insert"]

_log = get_logger(__name__)
# backends whose tracking pass leaves the frame's K/V in the cache's scratch (ONNX Runtime reads
# the cache as graph inputs and writes nothing back; the simulated backend keeps no real K/V)
_SCRATCH_WRITERS = frozenset({"torch"})


def _insertable(backend: Backend, request: RebuildRequest, compaction: MapCompactionConfig) -> bool:
    previous = request.previous
    return (
        compaction.incremental_keyframes
        and request.cause is RebuildCause.KEYFRAME
        and previous is not None
        and bool(request.keep)
        and previous.insertions < compaction.rebuild_every
        and previous.preprocessing == request.candidate.preprocessing
        and not previous.cache.quantized  # its pass leaves no per-layer scratch to adopt
        and backend.info.backend in _SCRATCH_WRITERS
    )


def _check_adopted(cache: KVCache) -> None:
    """The adopted frame's K/V must be finite (the rest of the cache was checked when made)."""
    T = cache.tokens_per_frame
    for layer in range(cache.layout.num_layers):
        if not (
            torch.isfinite(cache.keys(layer)[:, :, -T:]).all()
            and torch.isfinite(cache.values(layer)[:, :, -T:]).all()
        ):
            raise BackendError(f"the insertion pass returned non-finite K/V (cache layer {layer})")


def insert_keyframe(
    backend: Backend,
    request: RebuildRequest,
    *,
    rejection: RejectionConfig,
    rebuild_below: float,
) -> RebuildOutcome | None:
    """Insert ``request.candidate`` into ``request.previous`` by one tracking pass; None when its
    confidence calls for a full rebuild (below ``rebuild_below`` x keyframe 0's)."""
    start = time.perf_counter()
    previous, candidate = request.previous, request.candidate
    assert previous is not None  # _insertable
    cache = previous.cache.clone()
    if request.evicted:
        cache.drop_keyframes(request.evicted)
    with cache.lock:  # the scratch is adopted before any other pass can overwrite it
        result = backend.track(candidate.image, cache, heads=HeadSet.ALL)
        if result.confidence_map is None or result.local_points is None:
            return None  # the backend computed no dense heads: a full pass makes them
        cache.adopt_scratch(candidate.keyframe_id)
    if not (np.isfinite(result.pose).all() and np.isfinite(result.confidence_map).all()):
        raise BackendError("the insertion pass returned non-finite poses or confidences")
    _check_adopted(cache)
    reference = request.keep[0].mean_confidence
    confidence = masked_mean(result.confidence_map, candidate.mask)
    if confidence < rebuild_below * reference:
        _log.info("insertion confidence low: full rebuild", confidence=confidence,
                  reference=reference, keyframe_id=candidate.keyframe_id)  # fmt: skip
        return None
    gauge = previous.gauge  # the pass ran in the map's raw frame
    inserted = Keyframe(
        keyframe_id=candidate.keyframe_id,
        frame_index=candidate.frame_index,
        timestamp=candidate.timestamp,
        image=candidate.image,
        mask=candidate.mask,
        T_world_cam=gauge.apply_to_pose(result.pose),
        confidence_map=result.confidence_map,
        local_points=result.local_points * np.float32(gauge.scale),  # world scale
        mean_confidence=confidence,
        sensor_depth=candidate.sensor_depth,
    )
    keyframes = (*request.keep, inserted)
    new_map = KeyframeMap(
        keyframes, cache, gauge, generation=request.generation, resolution=previous.resolution,
        preprocessing=previous.preprocessing, insertions=previous.insertions + 1,
        world=previous.world,
    )  # fmt: skip
    accepted = not rejection.enabled or confidence >= rejection.ratio * reference
    return RebuildOutcome(
        request=request,
        new_map=new_map,
        accepted=accepted,
        candidate_confidence=confidence,
        reference_confidence=reference,
        correction=keyframe_corrections(request.keep, keyframes),  # none: they did not move
        map_ms=(time.perf_counter() - start) * 1e3,
    )


def rebuild_or_insert(
    backend: Backend,
    request: RebuildRequest,
    *,
    rejection: RejectionConfig,
    align_gauge: bool = True,
    compaction: MapCompactionConfig | None = None,
    object_masked: bool = False,
    cache_storage: str | None = None,
) -> RebuildOutcome:
    """An insertion when ``compaction`` allows one and it succeeds, else a full ``build_map``
    (a quantised map, ``cache_storage``, is always rebuilt: see ``KVCache.adopt_scratch``)."""
    if compaction is not None and _insertable(backend, request, compaction):
        outcome = insert_keyframe(
            backend, request, rejection=rejection, rebuild_below=compaction.rebuild_below
        )
        if outcome is not None:
            return outcome
    return build_map(
        backend, request, rejection=rejection, align_gauge=align_gauge, compaction=compaction,
        object_masked=object_masked, cache_storage=cache_storage,
    )  # fmt: skip

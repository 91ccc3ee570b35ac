"""One map rebuild: a mapping pass over the kept keyframes plus a candidate, aligned into the world
frame, turned into a new ``KeyframeMap``, and judged by the rejection rule.

Pure with respect to the tracker: it reads an immutable request (the previous map is a frozen
``KeyframeMap``) and returns an immutable outcome, so it can run on the mapping worker thread while
the tracker keeps tracking against the previous map. Installing the outcome is the tracker's job.
"""

from __future__ import annotations

import enum
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch

from kvtracker_sdk.backends.base import Backend, MapResult
from kvtracker_sdk.cache.keyframe_map import Keyframe, KeyframeMap
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.cache.pruning import object_token_mask, prune_cache
from kvtracker_sdk.config import MapCompactionConfig, RejectionConfig
from kvtracker_sdk.errors import BackendError, MapPreprocessingError
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.tracking.core.gauge import (
    Correction,
    anchor_gauge,
    depth_scale,
    estimate_gauge,
    keyframe_corrections,
)
from kvtracker_sdk.tracking.core.quality import masked_mean
from kvtracker_sdk.tracking.world.metric_scale import DepthScaleFit, fit_depth_scale
from kvtracker_sdk.world import MapWorld, ScaleSource

__all__ = [
    "KeyframeCandidate",
    "RebuildCause",
    "RebuildOutcome",
    "RebuildRequest",
    "build_map",
    "compact_cache",
]


@dataclass(frozen=True)
class KeyframeCandidate:
    """A tracked frame proposed as a keyframe (image and mask at model resolution)."""

    keyframe_id: int
    frame_index: int
    timestamp: float | None
    image: np.ndarray  # uint8 [h, w, 3]
    mask: np.ndarray | None  # bool [h, w]
    preprocessing: str  # name of the preprocessing that made ``image`` (see kvtracker_sdk.preprocess)
    sensor_depth: np.ndarray | None = None  # float32 [h, w] metres at model resolution (0 = hole)


class RebuildCause(str, enum.Enum):
    """Why a mapping pass runs; its value is what events (``MapUpdatedEvent.cause``) and logs
    say."""

    BOOTSTRAP = "bootstrap"  # the first map: the frame becomes keyframe 0
    KEYFRAME = "keyframe"  # a keyframe candidate joins the current map
    NEW_MAP = "new_map"  # a new map after a relocalisation timeout (policy ``new_map``)

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class RebuildRequest:
    """What to map: ``keep`` (keyframe 0 first, world frame) plus ``candidate``.

    ``previous`` is None for a bootstrap (first map, or a new map after a relocalisation timeout):
    then ``keep`` is empty and the candidate becomes keyframe 0 at the identity.
    """

    previous: KeyframeMap | None
    keep: tuple[Keyframe, ...]
    evicted: tuple[int, ...]
    candidate: KeyframeCandidate
    cause: RebuildCause
    generation: int  # generation the new map gets if accepted
    # a bootstrap after a lost map: keyframe 0's mean confidence must reach this absolute floor
    min_confidence: float | None = None
    # take the gauge's scale from the keyframes' sensor depth (a bootstrap with a depth frame, or
    # a map already metric by depth) instead of from the previous map's depths: metres, no drift
    anchor_to_depth: bool = False


@dataclass(frozen=True)
class RebuildOutcome:
    """The rebuilt map and the rejection verdict."""

    request: RebuildRequest
    new_map: KeyframeMap
    accepted: bool
    candidate_confidence: float  # the candidate's (masked) mean confidence in this pass
    reference_confidence: float  # keyframe 0's in this pass (a floored bootstrap: the floor)
    correction: Correction  # how the kept keyframes moved in the world frame
    map_ms: float
    # this pass's depth against the keyframes' sensor depth (metres per raw unit); None without
    depth_fit: DepthScaleFit | None = None


def _stack_masks(masks: Sequence[np.ndarray | None], size: tuple[int, int]) -> np.ndarray | None:
    """[N, h, w] masks for the pass: None if no frame has one, all-true where one lacks it."""
    if all(m is None for m in masks):
        return None
    return np.stack([m if m is not None else np.ones(size, dtype=bool) for m in masks])


def _anchors_world(request: RebuildRequest) -> bool:
    """Whether this pass fixes a new world frame (at its first frame) rather than joining one."""
    return request.previous is None or not request.keep


def _gauge(
    request: RebuildRequest, raw_poses: np.ndarray, raw_points: np.ndarray, align: bool,
    metric_scale: float | None = None,
) -> Sim3:
    """``metric_scale``: metres per raw unit from sensor depth; when given it sets the scale."""
    if not align:
        return Sim3.identity()  # debug: stay in the pass's raw frame
    if _anchors_world(request):
        return anchor_gauge(raw_poses[0], 1.0 if metric_scale is None else metric_scale)
    shared = len(request.keep)
    scale = metric_scale if metric_scale is not None else depth_scale(
        [kf.local_points for kf in request.keep],
        list(raw_points[:shared]),
        [kf.mask for kf in request.keep],
    )
    world_poses = np.stack([kf.T_world_cam for kf in request.keep])
    return estimate_gauge(world_poses, raw_poses[:shared], scale)


def _check_finite(poses: np.ndarray, confidence: np.ndarray, cache: KVCache) -> None:
    """Non-finite network output (NaN/inf weights or K/V) must never become a map."""
    if not (np.isfinite(poses).all() and np.isfinite(confidence).all()):
        raise BackendError("the mapping pass returned non-finite poses or confidences")
    for layer in range(cache.layout.num_layers):
        keys, values = cache.keys(layer), cache.values(layer)
        if not (torch.isfinite(keys).all() and torch.isfinite(values).all()):
            raise BackendError(f"the mapping pass returned non-finite K/V (cache layer {layer})")


def compact_cache(
    cache: KVCache,
    masks: Sequence[np.ndarray | None],
    backend: Backend,
    compaction: MapCompactionConfig,
    *,
    object_masked: bool,
) -> None:
    """Prune a fresh mapping pass's cache as ``compaction`` says (``cache/pruning.py``).

    ``object_masked``: the frames were masked to the object (black elsewhere), so the tokens of
    patches outside the keyframes' dilated ``masks`` [h, w] may go too."""
    info = backend.info
    allowed = None
    if object_masked and compaction.object_tokens and any(m is not None for m in masks):
        allowed = object_token_mask(
            masks,
            patch_size=info.patch_size,
            extra_tokens_per_frame=info.extra_tokens_per_frame,
            dilation_patches=compaction.object_dilation_patches,
        )
    if compaction.keep_ratio is not None or allowed is not None:
        prune_cache(
            cache,
            keep_ratio=compaction.keep_ratio or 1.0,
            extra_tokens_per_frame=info.extra_tokens_per_frame,
            allowed=allowed,
            score=compaction.prune_score,
        )


def _mapping_pass(
    backend: Backend, request: RebuildRequest
) -> tuple[list[Keyframe | KeyframeCandidate], tuple[int, int], MapResult]:
    """The mapping pass over the kept keyframes and the candidate: (its frames, the model image
    size (h, w), the backend's checked result)."""
    previous, candidate = request.previous, request.candidate
    if previous is not None and previous.preprocessing != candidate.preprocessing:
        raise MapPreprocessingError(
            f"cannot add a frame prepared by {candidate.preprocessing!r} to a map whose "
            f"keyframes were prepared by {previous.preprocessing!r}"
        )
    sources: list[Keyframe | KeyframeCandidate] = [*request.keep, request.candidate]
    images = np.stack([s.image for s in sources])  # [N, h, w, 3] uint8
    size = (int(images.shape[1]), int(images.shape[2]))
    result = backend.map(images, _stack_masks([s.mask for s in sources], size))
    if result.num_frames != len(sources) or result.cache.num_keyframes != len(sources):
        raise BackendError(
            f"mapping pass over {len(sources)} frames returned {result.num_frames} poses and a "
            f"cache of {result.cache.num_keyframes} keyframes"
        )
    _check_finite(result.poses, result.confidence, result.cache)
    return sources, size, result


def _gauge_and_world(
    request: RebuildRequest, result: MapResult, align_gauge: bool, depth_fit: DepthScaleFit | None
) -> tuple[Sim3, MapWorld]:
    """The new map's gauge (raw network frame -> world) and its world's description: scale from
    the sensor's depth when the request anchors to it and the fit succeeded."""
    anchored = request.anchor_to_depth and depth_fit is not None
    gauge = _gauge(request, result.poses, result.local_points, align_gauge,
                   depth_fit.scale if anchored and depth_fit is not None else None)
    previous = request.previous
    world = previous.world if previous is not None else MapWorld()
    if anchored and depth_fit is not None:
        world = replace(world, scale_source=ScaleSource.DEPTH,
                        scale_uncertainty=depth_fit.relative_uncertainty)
    return gauge, world


def _world_keyframes(
    sources: Sequence[Keyframe | KeyframeCandidate], result: MapResult, gauge: Sim3,
    anchors_world: bool,
) -> tuple[Keyframe, ...]:
    """The pass's frames as keyframes in the world frame (poses and local points through
    ``gauge``); ``anchors_world``: keyframe 0's camera is the world frame."""
    world_poses = gauge.apply_to_pose(result.poses)
    if anchors_world:
        # keyframe 0's camera IS the world frame: its pose is the identity by definition.
        # Computed as gauge(raw pose) it is R0^T R0, the identity only to how orthonormal the
        # network's float32 R0 is and how the CPU's kernels rounded it (differing in the last
        # bits between instruction sets and thread counts), so it is set, not computed.
        world_poses[0] = np.eye(4)
    return tuple(
        Keyframe(
            keyframe_id=source.keyframe_id,
            frame_index=source.frame_index,
            timestamp=source.timestamp,
            image=source.image,
            mask=source.mask,
            T_world_cam=world_poses[i],
            confidence_map=result.confidence[i],
            local_points=result.local_points[i] * np.float32(gauge.scale),  # world scale
            mean_confidence=masked_mean(result.confidence[i], source.mask),
            sensor_depth=source.sensor_depth,
        )
        for i, source in enumerate(sources)
    )


def build_map(
    backend: Backend,
    request: RebuildRequest,
    *,
    rejection: RejectionConfig,
    align_gauge: bool = True,
    compaction: MapCompactionConfig | None = None,
    object_masked: bool = False,
    cache_storage: str | None = None,
) -> RebuildOutcome:
    """Run the mapping pass for ``request`` and build the new map (see module docstring);
    ``compaction`` prunes its cache (``compact_cache``), then ``cache_storage`` ``"int8"`` /
    ``"fp8"`` quantises it (None: as it came)."""
    start = time.perf_counter()
    candidate_frame = request.candidate
    sources, size, result = _mapping_pass(backend, request)
    depth_fit = fit_depth_scale(
        [s.sensor_depth for s in sources], [points[..., 2] for points in result.local_points],
        list(result.confidence), [s.mask for s in sources], patch_size=backend.info.patch_size,
    )
    gauge, world = _gauge_and_world(request, result, align_gauge, depth_fit)
    keyframes = _world_keyframes(sources, result, gauge, align_gauge and _anchors_world(request))
    cache = result.cache
    cache.relabel_keyframes([kf.keyframe_id for kf in keyframes])
    if compaction is not None:  # pruned first: scores from the exact keys, fewer to quantise
        compact_cache(
            cache, [s.mask for s in sources], backend, compaction, object_masked=object_masked
        )
    if cache_storage is not None:
        cache = cache.to(storage=cache_storage)
    new_map = KeyframeMap(
        keyframes, cache, gauge, generation=request.generation, resolution=size,
        preprocessing=candidate_frame.preprocessing, world=world,
    )
    reference = keyframes[0].mean_confidence
    candidate = keyframes[-1].mean_confidence
    if request.previous is None and request.min_confidence is not None:
        # a new map must start from a frame confident in absolute terms, not relative to itself
        reference = request.min_confidence
        accepted = candidate >= reference
    else:
        judged = request.previous is not None and rejection.enabled
        accepted = not judged or candidate >= rejection.ratio * reference
    return RebuildOutcome(
        request=request,
        new_map=new_map,
        accepted=accepted,
        candidate_confidence=candidate,
        reference_confidence=reference,
        correction=keyframe_corrections(request.keep, keyframes),
        map_ms=(time.perf_counter() - start) * 1e3,
        depth_fit=depth_fit,
    )

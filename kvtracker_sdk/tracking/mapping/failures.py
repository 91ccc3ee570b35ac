"""Backend failures seen by the tracker: typed errors around the cause, and the retry backoff.

A backend may raise anything (a network's ``torch._C._LinAlgError`` on NaN weights, a driver
error, an ``onnxruntime`` failure) or return non-finite numbers. The tracker never lets one out of
``push_frame``: a failed **tracking** pass gives a frame result carrying a ``TrackingFailedError``;
a failed **mapping** pass keeps the current map, is reported once (event and ``MapStatus``), and the
next pass waits an exponentially growing number of frames (``backoff_frames``) so a persistent
failure costs one pass now and then, not one per frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from kvtracker_sdk.backends.base import Backend, TrackResult
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.errors import MappingFailedError, TrackingFailedError
from kvtracker_sdk.tracking.mapping.map_builder import RebuildRequest
from kvtracker_sdk.types import HeadSet

__all__ = [
    "FIRST_BACKOFF_FRAMES",
    "MAX_BACKOFF_FRAMES",
    "MappingFailure",
    "backoff_frames",
    "mapping_error",
    "track_checked",
]

FIRST_BACKOFF_FRAMES = 1  # after one failure the next pass may start one frame later
MAX_BACKOFF_FRAMES = 64  # ~2 s at 30 Hz: a recovered backend is used again soon enough


def backoff_frames(consecutive: int) -> int:
    """Frames to wait after ``consecutive`` (>= 1) failed mapping passes in a row: 1, 2, 4, ... 64."""
    return min(FIRST_BACKOFF_FRAMES << min(max(consecutive - 1, 0), 30), MAX_BACKOFF_FRAMES)


@dataclass(frozen=True)
class MappingFailure:
    """What ``MapKeeper.collect`` returns for a failed pass (the map is unchanged)."""

    request: RebuildRequest
    error: MappingFailedError
    consecutive: int
    retry_at_frame: int


def mapping_error(exc: BaseException, request: RebuildRequest) -> MappingFailedError:
    """``exc`` as a ``MappingFailedError`` naming the pass (the original as ``__cause__``)."""
    if isinstance(exc, MappingFailedError):
        return exc
    error = MappingFailedError(
        f"{request.cause.value} mapping pass for frame {request.candidate.frame_index} failed: "
        f"{type(exc).__name__}: {exc}"
    )
    error.__cause__ = exc
    return error


def _finite(value: float | np.ndarray | None) -> bool:
    if value is None:
        return True
    if isinstance(value, float):
        return math.isfinite(value)
    return bool(np.isfinite(value).all())


def track_checked(
    backend: Backend, image: np.ndarray, cache: KVCache, heads: HeadSet, frame_index: int
) -> TrackResult:
    """``backend.track`` whose failures (an exception, or a non-finite pose or confidence — e.g. a
    map whose K/V hold NaN) raise ``TrackingFailedError`` with the original as ``__cause__``.
    """
    try:
        tracked = backend.track(image, cache, heads=heads)
    except Exception as exc:  # any backend exception: the frame loop must go on
        raise TrackingFailedError(
            f"tracking frame {frame_index} failed: {type(exc).__name__}: {exc}"
        ) from exc
    if not (
        _finite(tracked.pose) and _finite(tracked.confidence) and _finite(tracked.confidence_map)
    ):
        raise TrackingFailedError(
            f"tracking frame {frame_index} returned a non-finite pose or confidence"
        )
    return tracked

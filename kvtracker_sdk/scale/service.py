"""``TrackerHost``: one device's tracker service — one backend, many sessions.

An actor per device (``ray_runtime.actor_class(TrackerHost)``; or a plain object in one process)
holds the model loaded once and a table ``session id -> Tracker``. Clients open a session
(optionally from a saved map, shipped once *by path*), send encoded frames (PNG/JPEG bytes) with
their capture timestamps, and get each frame's result as a plain dict. A session moves between
hosts through its map file: ``save_session`` on one, ``open_session(map_path=...)`` on another.

A simulated session (no weights) carries its own ``SimulatedBackend``: the simulation is driven by
that stream's ground truth, so it cannot be shared the way a network's weights are.
"""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING, Any

import numpy as np

from kvtracker_sdk.errors import ConfigError, InputError, StateError
from kvtracker_sdk.scale.manifest import ModelSpec, SimulatedSpec
from kvtracker_sdk.scale.model_cache import ModelCache
from kvtracker_sdk.scale.sequence_run import torch_threads

if TYPE_CHECKING:
    from kvtracker_sdk.backends.base import Backend
    from kvtracker_sdk.tracking.facade.tracker import Tracker
    from kvtracker_sdk.types import FrameResult

__all__ = ["TrackerHost", "decode_frame", "result_to_dict", "simulated_backend"]

_MAX_ENCODED_BYTES = 64 << 20  # one encoded frame; a 4K PNG is ~25 MB


def simulated_backend(spec: SimulatedSpec) -> Backend:
    """The simulated backend of a stream (its ground truth and noise)."""
    from kvtracker_sdk.scale.sequence_run import simulated_sequence

    backend, _frames, _truth = simulated_sequence(spec)
    return backend


def decode_frame(encoded: bytes) -> np.ndarray:
    """PNG/JPEG bytes -> HxWx3 uint8 RGB; InputError if they are not an image."""
    import cv2

    if not isinstance(encoded, bytes | bytearray | memoryview) or not 0 < len(encoded) <= _MAX_ENCODED_BYTES:
        raise InputError("a frame must be 1 byte to 64 MiB of encoded image data")
    image = cv2.imdecode(np.frombuffer(encoded, dtype=np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise InputError("the frame bytes are not a decodable image (PNG, JPEG, ...)")
    return np.ascontiguousarray(image[:, :, ::-1])


def result_to_dict(result: FrameResult) -> dict[str, Any]:
    """A frame result as plain data (what crosses process boundaries)."""
    pose = result.pose
    return {
        "frame_index": result.frame_index,
        "timestamp": result.timestamp,
        "state": result.state.value,
        "reason": result.reason.value,
        "pose_valid": result.pose_valid,
        "T_world_cam": None if pose is None else pose.T_world_cam.tolist(),
        "confidence": result.confidence,
        "keyframe_id": result.keyframe_id,
        "map_generation": result.map_generation,
        # object mode: where the object is (x0, y0, x1, y1 pixels) and its frame in the camera's
        "region": None if result.region is None else {
            "box": list(result.region.box), "context_box": list(result.region.context_box),
            "source": result.region.source.value},
        "T_cam_object": None if result.T_cam_object is None else result.T_cam_object.tolist(),
    }


class TrackerHost:
    """Sessions of one device. Methods are safe to call from several threads; one session's
    frames are processed in the order they arrive (the tracker serialises them)."""

    def __init__(self, model_json: str | None = None, *, threads: int = 1) -> None:
        # model_json: a backend spec (runs.backends.BackendSpec: kind, weights, dtype, options)
        self._models = ModelCache(ModelSpec.model_validate_json(model_json) if model_json else None,
                                  threads=threads)
        self._threads = threads
        self._sessions: dict[str, Tracker] = {}
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ sessions
    def open_session(
        self,
        session_id: str,
        *,
        config: dict[str, Any] | None = None,
        map_path: str | None = None,
        simulated: dict[str, Any] | None = None,
        camera: dict[str, Any] | None = None,
    ) -> dict[str, Any]:
        """Start a session (fresh, or relocalising against the map at ``map_path``). A simulated
        session gives its ``simulated`` spec; others run on this host's model. ``camera``: the
        stream's intrinsics as ``Camera.to_dict()`` gives them (its frames are undistorted)."""
        from kvtracker_sdk.geometry.camera import Camera
        from kvtracker_sdk.runs.session import open_tracker

        with self._lock:
            if session_id in self._sessions:
                raise StateError(f"session {session_id!r} is already open")
        backend = (
            simulated_backend(SimulatedSpec.model_validate(simulated))
            if simulated is not None
            else self._models.get()
        )
        intrinsics = Camera.from_dict(camera) if camera is not None else None
        tracker = open_tracker(config if map_path is not None else (config or {}), backend,
                               camera=intrinsics, load_map=map_path)
        with self._lock:
            if session_id in self._sessions:  # opened concurrently meanwhile
                tracker.close()
                raise StateError(f"session {session_id!r} is already open")
            self._sessions[session_id] = tracker
        return {"session_id": session_id, "state": tracker.state.value}

    def push(
        self, session_id: str, frame: bytes, timestamp: float,
        bbox: tuple[float, float, float, float] | None = None,
    ) -> dict[str, Any]:
        """Track one encoded frame of ``session_id``; its result as plain data. ``bbox``: the
        object's box (object mode: needed with the session's first frame only)."""
        tracker = self._session(session_id)
        image = decode_frame(frame)
        with torch_threads(self._threads):
            result = tracker.push_frame(image, timestamp=timestamp, bbox=bbox)
        return result_to_dict(result)

    def save_session(self, session_id: str, path: str) -> dict[str, Any]:
        """Save the session's map (atomically) so another host can resume it."""
        info = self._session(session_id).save_map(path)
        return {"path": path, "keyframe_ids": list(info.keyframe_ids)}

    def close_session(self, session_id: str) -> None:
        with self._lock:
            tracker = self._sessions.pop(session_id, None)
        if tracker is None:
            raise ConfigError(f"no session {session_id!r}")
        tracker.close()

    def sessions(self) -> list[str]:
        with self._lock:
            return sorted(self._sessions)

    def model_loads(self) -> int:
        return self._models.loads

    def close(self) -> None:
        with self._lock:
            trackers, self._sessions = list(self._sessions.values()), {}
        for tracker in trackers:
            tracker.close()
        self._models.close()

    def _session(self, session_id: str) -> Tracker:
        with self._lock:
            tracker = self._sessions.get(session_id)
        if tracker is None:
            raise ConfigError(f"no session {session_id!r}")
        return tracker

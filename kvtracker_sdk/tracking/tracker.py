"""``Tracker``: the SDK's facade — frames in, poses out.

``push_frame`` validates and resizes a frame (``frame_input``) and hands it to the ``FrameLoop``
(``frame_loop``: track, judge confidence, move through the state table, propose keyframes, install
rebuilds). Events are queued while the tracker's lock is held and delivered after it is released,
on the calling thread (``events``). Maps are saved, loaded and exported through ``persistence``.

Thread safety: every public method may be called from any thread. ``push_frame`` calls are
serialised; ``snapshot()``, ``get_pose``, ``state``, ``reason``, ``map_status`` and
``keyframe_map`` read immutable values and never block on a frame or a rebuild. Methods that wait
for a rebuild (``wait_for_map``, ``save_map``, ``set_backend``, exports) wait *without* the lock, so
``push_frame`` on a camera thread never stalls behind them.

Backend failures never leave ``push_frame`` (``failures``): a failed tracking pass gives a result
with ``error`` set, a failed mapping pass keeps the current map and backs off; both send an
``on_backend_failed`` event.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from kvtracker_sdk.backends.base import Backend, BackendInfo
from kvtracker_sdk.backends.frame_checks import reads_quantized_caches
from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.config import ObjectPreprocessing, TrackerConfig, TrackingMode
from kvtracker_sdk.errors import (
    BackendMismatchError,
    ConfigError,
    InputError,
    MissingDependencyError,
    StateError,
)
from kvtracker_sdk.geometry.camera import Camera, IntrinsicsSource
from kvtracker_sdk.io.map_file import MapInfo
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.tracking import persistence
from kvtracker_sdk.tracking.events import EventBus, EventSource
from kvtracker_sdk.tracking.frame_input import FramePreparer, family_preprocessing
from kvtracker_sdk.tracking.frame_loop import FrameLoop
from kvtracker_sdk.tracking.intrinsics import FrameIntrinsics
from kvtracker_sdk.tracking.live_intake import ErrorCallback, LiveIntake, LiveStats, ResultCallback
from kvtracker_sdk.tracking.object_region import OBJECT_NOT_FOUND_HINT, RegionPropagator
from kvtracker_sdk.tracking.persistence import ConfigOverride, PathLike
from kvtracker_sdk.tracking.segmenter import Segmenter
from kvtracker_sdk.types import (
    FrameResult,
    MapStatus,
    ObjectFrame,
    ObjectRegion,
    Pose,
    StateReason,
    TrackedPose,
    TrackerSnapshot,
    TrackingState,
)

__all__ = ["Tracker"]

_log = get_logger(__name__)
_S, _R = TrackingState, StateReason


def _ms(since: float) -> float:
    return (time.perf_counter() - since) * 1e3


class Tracker(EventSource):
    """Tracks a camera (scene mode) or an object (object mode) from RGB frames.

    ``Tracker(config, backend)``: ``config`` is a ``TrackerConfig`` (or a dict of its fields, or
    None for defaults); ``backend`` implements ``kvtracker_sdk.backends.base.Backend``. The tracker
    does not close a backend it was given; it closes one it created (``from_pretrained``).
    Callbacks (``on_*``, see ``events.EventSource``) run on the thread that called the method
    causing them (see ``events``). ``camera``: the input images' intrinsics for the session
    (``set_camera`` changes them; ``push_frame(camera=...)`` overrides them for one frame);
    distorted frames are undistorted. ``segmenter``: object mode's ``Segmenter`` (optional; see
    ``set_segmenter``).
    """

    def __init__(
        self, config: TrackerConfig | Mapping[str, Any] | None, backend: Backend, *,
        camera: Camera | None = None, segmenter: Segmenter | None = None,
    ) -> None:
        cfg = config if isinstance(config, TrackerConfig) else TrackerConfig.from_dict(config or {})
        self._preparer = FramePreparer(
            cfg, patch_size=backend.info.patch_size, family=backend.info.family,
            declared=getattr(backend, "preprocessing", None),
        )
        cfg = self._preparer.config  # an unset resolution becomes the family's default
        _check_cache_dtype(cfg, backend.info)
        self._config = cfg
        self._owns_backend = False
        self._events = EventBus()
        self._loop = FrameLoop(
            cfg, backend, self._events, preprocessing=self._preparer.preprocessing.name
        )
        self._keeper = self._loop.keeper
        self._lock = threading.RLock()
        self._input_size: tuple[int, int] | None = None  # of the session's frames
        self._frames = 0  # frame indices are never reused by one tracker
        self._closed = False
        self._camera = _checked_camera(camera)
        crops = cfg.mode is TrackingMode.OBJECT and (
            cfg.object.preprocessing is ObjectPreprocessing.CROP
        )
        self._intrinsics = FrameIntrinsics(estimate=not crops)  # per-frame crops: no map-wide fit
        self._last_intrinsics: tuple[Camera, IntrinsicsSource] | None = None
        self._intake: LiveIntake | None = None  # made by the first submit()
        self._intake_lock = threading.Lock()  # never the tracker's lock: submit must not wait
        self._object_mode = cfg.mode is TrackingMode.OBJECT
        self._regions = RegionPropagator(margin=cfg.object.crop_margin_px,
                                         models=self._keeper.objects)
        self._segmenter = _checked_segmenter(segmenter)
        self._searched = 0  # frames tracked unmasked in a row without finding the object

    @classmethod
    def from_pretrained(cls, weights: str | Path, **config: Any) -> Tracker:
        """A tracker over the PyTorch backend loaded from ``weights`` (file, folder or hub id);
        ``config`` holds ``TrackerConfig`` fields (validated before the weights load)."""
        cfg = TrackerConfig.from_dict(config)
        try:
            from kvtracker_sdk.backends.torch_backend import TorchBackend
        except ImportError as exc:
            raise MissingDependencyError(f"the PyTorch backend cannot be imported: {exc}") from exc
        tracker = cls(cfg, TorchBackend.from_pretrained(weights))
        tracker._owns_backend = True
        return tracker

    @classmethod
    def from_map(
        cls, path: PathLike, backend: Backend, config: ConfigOverride = None, *,
        rebuild: bool = False, camera: Camera | None = None,
    ) -> Tracker:
        """A tracker relocalising against the map saved at ``path`` by ``backend``'s model.
        ``config``: None keeps the map's saved one; a dict changes some of its fields.

        A map whose keyframes another preprocessing prepared (saved before the SDK followed the
        official pipelines: header without ``preprocessing``) is tracked against with frames
        prepared its way, and not extended; ``rebuild=True`` lets new keyframes extend it (also
        prepared its way). Extending it otherwise raises ``MapPreprocessingError``.
        ``camera``: this session's intrinsics; when they differ from the map's saved ones a
        WARNING ``map_camera_mismatch`` is logged (``persistence.check_map_camera``)."""
        loaded = persistence.load_tracker_map(
            path, backend.info, config, backend_preprocessing=family_preprocessing(
                backend.info.family, getattr(backend, "preprocessing", None)).name)
        persistence.check_map_camera(loaded.info, camera, str(path))
        tracker = cls(loaded.config, backend, camera=camera)
        tracker._install_loaded_map(loaded.keyframe_map, rebuild=rebuild)
        return tracker

    # ------------------------------------------------------------------ read-only views
    @property
    def config(self) -> TrackerConfig:
        return self._config

    @property
    def backend(self) -> Backend:
        return self._loop.backend

    @property
    def state(self) -> TrackingState:
        return self._loop.state

    @property
    def reason(self) -> StateReason:
        """Why the tracker is in ``state``; read both at once through ``snapshot()``."""
        return self._loop.reason

    def snapshot(self) -> TrackerSnapshot:
        """State, reason, last frame, last valid pose and map generation, read atomically."""
        return self._loop.snapshot

    @property
    def keyframe_map(self) -> KeyframeMap | None:
        """The current map (immutable; replaced as a whole on every accepted rebuild)."""
        return self._keeper.map

    @property
    def map_status(self) -> MapStatus:
        return replace(self._keeper.status(), failed_tracks=self._loop.failed_tracks)

    def get_pose(self) -> Pose | None:
        """The last valid ``T_world_cam`` (None before the first, and after a reset); which frame
        it belongs to: ``get_tracked_pose()``."""
        tracked = self._loop.snapshot.pose
        return None if tracked is None else tracked.pose

    def get_tracked_pose(self) -> TrackedPose | None:
        """The last valid pose with its frame index and timestamp (None like ``get_pose``)."""
        return self._loop.snapshot.pose

    @property
    def camera(self) -> Camera | None:
        """The session's given intrinsics (None: predicted or estimated per frame)."""
        return self._camera

    @property
    def object_frame(self) -> ObjectFrame | None:
        """Object mode: the object's frame and extent in the world frame (``ObjectFrame``: origin
        at the object centre; z along ``up``, the support plane's normal, for an object standing
        on one, else axes of keyframe 0; an oriented box of the fused object points); None in
        scene mode and before the map holds object points."""
        if not self._object_mode:
            return None
        with self._call():
            return self._regions.object_frame(self._keeper.map)

    @property
    def object_region(self) -> ObjectRegion | None:
        """Object mode: the region of the last frame (``FrameResult.region``), None before one."""
        return self._regions.last

    def set_segmenter(self, segmenter: Segmenter | None) -> None:
        """Object mode: ask ``segmenter`` for the object's mask in every frame pushed without a
        mask or box, prompting it with the predicted region (None: use the prediction itself)."""
        checked = _checked_segmenter(segmenter)
        with self._call():
            self._segmenter = checked

    def set_camera(self, camera: Camera | None) -> None:
        """Give (or with None, forget) the input images' intrinsics from the next frame on."""
        checked = _checked_camera(camera)
        with self._call():
            self._camera = checked

    # ------------------------------------------------------------------ session control
    def initialize(self, map: PathLike | None = None, *, rebuild: bool = False) -> None:
        """Start a fresh session: without ``map``, no map and state INIT; with ``map``, relocalise
        against the map saved at that path under this tracker's configuration (its mode and
        resolution must be the map's; ``rebuild`` as in ``from_map``). A load that fails raises
        and changes nothing."""
        if map is None:
            self.reset()
            return
        loaded = persistence.load_tracker_map(
            map, self.backend.info, self._config,
            backend_preprocessing=self._preparer.preprocessing.name)
        persistence.check_map_camera(loaded.info, self._camera, str(map))
        self._install_loaded_map(loaded.keyframe_map, rebuild=rebuild)

    def reset(self) -> None:
        """Drop the map (a pending rebuild is discarded) and return to INIT with reason RESET."""
        with self._call():
            self._loop.drop_map(_R.RESET)
            self._input_size = None
            self._regions.reset()
            self._searched = 0
            if self.state is not _S.INIT:
                self._loop.change(_S.INIT, _R.RESET, None)

    def _install_loaded_map(self, kf_map: KeyframeMap, *, rebuild: bool = False) -> None:
        """Persistence seam: install a saved map and relocalise against it (RELOCALIZING,
        MAP_LOADED). The caller has checked the map's model fingerprint."""
        with self._call():
            if kf_map.cache.layout != self.backend.info.layout:
                raise BackendMismatchError(
                    f"map cache layout {kf_map.cache.layout} != backend {self.backend.info.layout}"
                )
            self._input_size = None
            self._regions.reset()
            self._searched = 0
            self._loop.install_loaded(kf_map, rebuild=rebuild)
            if not self._keeper.extendable:
                _log.warning(
                    "map made by another preprocessing: tracking only, no new keyframes",
                    map_preprocessing=kf_map.preprocessing,
                    preprocessing=self._preparer.preprocessing.name,
                    hint="load it with rebuild=True to extend it",
                )

    def set_backend(self, backend: Backend) -> Backend:
        """Swap backends between frames (e.g. torch -> onnx); returns the previous one, unclosed.

        The two must compute the same function: equal ``info.fingerprint`` and ``info.layout``.
        Pending rebuilds are waited for (without blocking ``push_frame``), and the map's cache is
        converted if the new backend computes in another dtype or on another device.
        """
        old, new = self._loop.backend.info, backend.info
        if old.fingerprint != new.fingerprint or old.layout != new.layout:
            raise BackendMismatchError(
                f"cannot swap {old.backend}/{old.model} (fingerprint {old.fingerprint}, layout "
                f"{old.layout}) for {new.backend}/{new.model} (fingerprint {new.fingerprint}, "
                f"layout {new.layout})"
            )
        _check_cache_dtype(self._config, new)
        while True:
            self._settle(timeout=None)  # rebuilds made by the old backend
            with self._call():
                if self._keeper.rebuilding:
                    continue  # a frame started another one meanwhile
                self._keeper.convert_cache(
                    new.dtype, new.device, dequantize=not reads_quantized_caches(new)
                )
                previous, self._loop.backend = self._loop.backend, backend
                self._owns_backend = False
                return previous

    def save_map(self, path: PathLike) -> MapInfo:
        """Save the map (after the pending rebuilds) atomically: ``path`` keeps its old content or
        holds the whole new map. StateError without a map; MapIOError if it cannot write."""
        kf_map = self._settled_map()
        return persistence.save_tracker_map(
            path, kf_map, self.backend.info, self._config, camera=self._map_camera()
        )

    def export_point_cloud(self, path: PathLike, **options: Any) -> int:
        """The map's point cloud as PLY; ``options`` and return: ``persistence``'s."""
        return persistence.export_point_cloud(self._settled_map(), path, **options)

    def export_trajectory(self, path: PathLike) -> int:
        """The keyframes' world poses as a TUM trajectory; returns the number of poses."""
        return persistence.export_trajectory(self._settled_map(), path)

    def wait_for_map(self, timeout: float | None = None) -> bool:
        """Wait for the rebuilds pending now (and a keyframe waiting for one) and install them;
        True when they are, False if ``timeout`` seconds passed first. Frames keep flowing."""
        return self._settle(timeout)

    def close(self) -> None:
        """Stop the live intake and the mapping worker (and close a backend this tracker
        created). Idempotent."""
        intake = self._intake
        if intake is not None:
            intake.close(drain=False)  # before the lock: its worker may be inside push_frame
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._keeper.close()
            if self._owns_backend:
                self._loop.backend.close()

    def __enter__(self) -> Tracker:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # ------------------------------------------------------------------ live intake
    def submit(
        self, image: np.ndarray, timestamp: float | None = None, *, mask: np.ndarray | None = None,
        bbox: Any = None, camera: Camera | None = None, captured_at: float | None = None,
    ) -> None:
        """Hand a frame to the live worker and return at once (``tracking/live_intake.py``).

        The worker always tracks the newest frame; one still waiting when a newer arrives is
        dropped and counted. Results: ``on_result`` callbacks and ``latest()``; counters and
        latency: ``stats``. ``timestamp`` defaults to the wall-clock time now (capture time).
        For live use, build the tracker with ``threading={"async_mapping": True}`` so that
        rebuilds do not pause tracking.
        """
        self._live().submit(image, timestamp, mask=mask, bbox=bbox, camera=camera,
                            captured_at=captured_at)

    def on_result(self, callback: ResultCallback) -> None:
        """``callback(FrameResult)`` after each frame the live worker processed (worker thread)."""
        self._live().on_result(callback)

    def on_frame_error(self, callback: ErrorCallback) -> None:
        """``callback(exception)`` when the live worker's ``push_frame`` raised (worker thread)."""
        self._live().on_error(callback)

    def latest(self) -> FrameResult | None:
        """The live worker's most recent result (None before the first)."""
        intake = self._intake
        return None if intake is None else intake.latest()

    @property
    def stats(self) -> LiveStats:
        """Live intake counters: submitted, processed, dropped, delivered FPS, latency."""
        intake = self._intake
        return LiveStats.empty() if intake is None else intake.stats

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Wait until the live worker has no frame pending or in progress."""
        intake = self._intake
        return True if intake is None else intake.wait_idle(timeout)

    def _live(self) -> LiveIntake:
        intake = self._intake
        if intake is None:
            with self._intake_lock:
                if self._closed:
                    raise StateError("the tracker is closed")
                if self._intake is None:
                    self._intake = LiveIntake(self)
                intake = self._intake
        return intake

    # ------------------------------------------------------------------ the frame loop
    def push_frame(
        self, image: np.ndarray, timestamp: float | None = None, mask: np.ndarray | None = None,
        bbox: Any = None, camera: Camera | None = None,
    ) -> FrameResult:
        """Track one RGB frame [H, W, 3] (uint8, or float in [0, 1]).

        ``mask`` (bool/int [H, W]) or ``bbox`` (x0, y0, x1, y1) select the object in object mode:
        required with the first frame, optional afterwards (a frame without one is tracked with
        the region predicted from the map, or the ``Segmenter``'s mask; the result's ``region``
        and ``T_cam_object`` say where the object is, ``tracking/object_region.py``); against a
        loaded object map, not needed at all (the whole frame is searched until the tracker
        relocalises; reason ``OBJECT_NOT_FOUND`` if it does not within
        ``object.search_frames`` frames). The result's ``pose`` is None without a map (INIT, MAPPING) or when the
        backend failed on this frame (``error``); ``pose_valid`` is False while relocalising or for
        a low-confidence frame. ``keyframe_id`` is set when the frame became a keyframe in this
        call (synchronous mapping; with asynchronous mapping the ``on_keyframe`` event reports it
        later). ``camera`` gives this frame's intrinsics (else the session's); the result's
        ``intrinsics`` are the input image's: given, predicted or estimated
        (``tracking/intrinsics.py``). Bad input raises an ``InputError`` subclass before anything
        changes; backend failures never raise.
        """
        start = time.perf_counter()
        with self._call():
            kf_map = self._keeper.map
            index = self._frames
            given = mask is not None or bbox is not None
            segmented, searching = None, False
            if self._object_mode and not given:
                mask, segmented = self._regions.input_mask(
                    image, index, kf_map, self._segmenter, min_side=self._preparer.patch_size)
                if mask is None and kf_map is not None:  # a loaded map, no pose yet: search
                    mask = self._regions.search_mask(image, min_side=self._preparer.patch_size)
                    searching = True
            prompt_ms = _ms(start)  # predicting the region (and asking the segmenter)
            frame = self._preparer.prepare(
                image, timestamp=timestamp, mask=mask, bbox=bbox,
                session_input_size=self._input_size,
                map_resolution=None if kf_map is None else kf_map.resolution,
                map_preprocessing=None if kf_map is None else kf_map.preprocessing,
                camera=_checked_camera(camera) if camera is not None else self._camera,
            )
            timings = {"preprocess": _ms(start) - prompt_ms}
            if segmented is not None:
                timings["segment"] = prompt_ms
            self._loop.predicted_K = None
            step = self._loop.step(frame, index, timings, keyframe_allowed=not searching)
            intrinsics, source = self._intrinsics.resolve(
                frame, self._loop.predicted_K, self._keeper.map
            )
            if intrinsics is not None and source is not None:
                self._last_intrinsics = (intrinsics, source)
            region, T_cam_object = None, None
            if self._object_mode:
                region_start = time.perf_counter()
                supplied = self._regions.supplied(frame.input_size, index, mask if given else None,
                                                  bbox if given else None, segmented)
                pose = step.pose.T_world_cam if step.valid and step.pose is not None else None
                region, T_cam_object = self._regions.observe(
                    index, self._keeper.map, T_world_cam=pose, camera=intrinsics,
                    supplied=supplied)
                timings["region"] = _ms(region_start) + (0.0 if segmented is not None
                                                          else prompt_ms)
                self._count_search(searching and not step.valid, index)
            # counted once the frame went through: an unexpected error leaves both as they were
            self._frames, self._input_size = index + 1, frame.input_size
            timings["total"] = _ms(start)
            result = FrameResult(
                index, frame.timestamp, self.state, self.reason, step.pose, step.valid,
                step.confidence, step.keyframe_id, self._loop.snapshot.map_generation, timings,
                {"rebuilding": self._keeper.rebuilding}, step.error, intrinsics, source,
                region, T_cam_object,
            )
        _log.debug("frame", frame_index=index, state=result.state.value, pose_valid=step.valid,
                   confidence=step.confidence,
                   **{f"{k}_ms": round(v, 3) for k, v in timings.items()})
        return result

    # ------------------------------------------------------------------ plumbing
    def _count_search(self, missed: bool, index: int) -> None:
        """Object mode: count frames searched in vain for a loaded map's object; the
        ``object.search_frames``-th sets the reason OBJECT_NOT_FOUND (the app must point at it)."""
        self._searched = self._searched + 1 if missed else 0
        if self._searched == self._config.object.search_frames and self.state is _S.RELOCALIZING:
            self._loop.change(_S.RELOCALIZING, _R.OBJECT_NOT_FOUND, index)
            _log.warning("the loaded map's object was not found in the whole frame",
                         frames=self._searched, hint=OBJECT_NOT_FOUND_HINT)

    def _map_camera(self) -> tuple[Camera, IntrinsicsSource] | None:
        """What a saved map records as its camera: the session's given one, else the last
        frame's reported intrinsics."""
        if self._camera is not None:
            return self._camera, IntrinsicsSource.GIVEN
        return self._last_intrinsics

    def _settled_map(self) -> KeyframeMap | None:
        """The map once the rebuilds pending now are installed (waits without the lock)."""
        self._settle(timeout=None)
        return self._keeper.map

    def _settle(self, timeout: float | None) -> bool:
        """Install the rebuilds pending or waiting at the call; True when done within ``timeout``
        seconds (None: however long it takes). Waits for the worker WITHOUT holding the lock:
        the camera thread keeps pushing frames (and may collect them itself) meanwhile."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._call():
            target = self._keeper.settle_target()
        while True:
            with self._call():
                index = max(self._frames - 1, 0)
                while self._keeper.rebuilding and self._loop.collect(index, {}) is not None:
                    pass  # a collected rebuild may start the waiting keyframe's
                if self._keeper.settled(target):
                    return True
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return False
            self._keeper.wait(left)

    @contextmanager
    def _call(self) -> Iterator[None]:
        """Hold the lock for a public call on an open tracker; deliver the events it queued after
        releasing the lock (also when the call raised: the app must learn of a state change)."""
        try:
            with self._lock:
                if self._closed:
                    raise StateError("the tracker is closed")
                yield
        finally:
            self._events.deliver()


def _check_cache_dtype(config: TrackerConfig, backend: BackendInfo) -> None:
    """ConfigError if the config asks for quantised maps a backend cannot track against."""
    if config.cache_dtype != "backend" and not reads_quantized_caches(backend):
        raise ConfigError(
            f"cache_dtype {config.cache_dtype!r} needs the PyTorch backend; the {backend.backend} "
            f"backend reads dense caches only (cache_dtype 'backend')"
        )


def _checked_segmenter(segmenter: Any) -> Segmenter | None:
    if segmenter is not None and not isinstance(segmenter, Segmenter):
        raise InputError(f"segmenter must have a segment(image, prompt) method, got {segmenter!r}")
    return segmenter


def _checked_camera(camera: Any) -> Camera | None:
    if camera is not None and not isinstance(camera, Camera):
        raise InputError(f"camera must be a kvtracker_sdk.Camera or None, got {camera!r}")
    return camera

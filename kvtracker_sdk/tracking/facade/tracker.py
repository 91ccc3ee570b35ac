"""``Tracker``: the SDK's facade — frames in, poses out.

``push_frame`` checks what it was given once, on entry (``frame_input``), then runs the checked
frame straight through: its mode's region (``frame_mode``; object mode only), its preparation for
the model (``model_input``), the ``FrameLoop``'s step (``frame_loop``: track, judge confidence,
move through the state table, propose keyframes, install rebuilds) and its mode's observation. Events are queued while the tracker's lock is held and delivered after it is released,
on the calling thread (``events``). Maps are saved, loaded and exported through ``persistence``.

The members an app needs less often are grouped in thin views over the tracker, each in its own
module and owning no state or lock: ``events`` (callback registration, ``tracker_events``),
``live`` (the live intake's results and counters, ``tracker_live``), ``object`` (object mode's
frame, region and segmenter, ``tracker_object``), ``world`` (known sizes that make the world
metric, ``tracker_world``) and ``export`` (point cloud, trajectory, ``tracker_export``). The
names they replaced still work for one release, with a warning (``tracker_renames``).

Thread safety: every public method may be called from any thread. ``push_frame`` calls are
serialised; ``snapshot()``, ``get_pose``, ``state``, ``reason``, ``map_status`` and
``keyframe_map`` read immutable values and never block on a frame or a rebuild. Methods that wait
for a rebuild (``wait_for_map``, ``save_map``, ``set_backend``, ``export``) wait *without* the
lock, so ``push_frame`` on a camera thread never stalls behind them.

Backend failures never leave ``push_frame`` (``failures``): a failed tracking pass gives a result
with ``error`` set, a failed mapping pass keeps the current map and backs off; both send an
``events.on_backend_failed`` event.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from kvtracker_sdk.backends.base import Backend, BackendInfo
from kvtracker_sdk.backends.frame_checks import reads_quantized_caches
from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.config import ObjectPreprocessing, TrackerConfig, TrackingMode
from kvtracker_sdk.errors import (
    BackendMismatchError,
    ConfigError,
    MissingDependencyError,
    StateError,
)
from kvtracker_sdk.geometry.camera import Camera, IntrinsicsSource
from kvtracker_sdk.io.map_file.map_file import MapInfo
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.preprocess.undistort import Undistorter
from kvtracker_sdk.tracking.core.events import EventBus
from kvtracker_sdk.tracking.core.frame_input import check_camera, check_frame
from kvtracker_sdk.tracking.core.intrinsics import FrameIntrinsics
from kvtracker_sdk.tracking.core.model_input import FramePreparer, family_preprocessing
from kvtracker_sdk.tracking.facade.tracker_events import TrackerEvents
from kvtracker_sdk.tracking.facade.tracker_export import TrackerExport
from kvtracker_sdk.tracking.facade.tracker_live import TrackerLive
from kvtracker_sdk.tracking.facade.tracker_object import TrackerObject, checked_segmenter
from kvtracker_sdk.tracking.facade.tracker_renames import renamed_member
from kvtracker_sdk.tracking.facade.tracker_world import TrackerWorld
from kvtracker_sdk.tracking.live.live_intake import LiveIntake
from kvtracker_sdk.tracking.loop.frame_loop import FrameLoop
from kvtracker_sdk.tracking.loop.states import TrackingEvent
from kvtracker_sdk.tracking.object.frame_mode import (
    FrameMode,
    ObjectFrames,
    SceneFrames,
)
from kvtracker_sdk.tracking.object.object_region import OBJECT_NOT_FOUND_HINT, RegionPropagator
from kvtracker_sdk.tracking.object.segmenter import Segmenter
from kvtracker_sdk.tracking.persistence import tracker_maps as persistence
from kvtracker_sdk.tracking.persistence.tracker_maps import ConfigOverride, PathLike
from kvtracker_sdk.types import (
    FrameResult,
    MapStatus,
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


class Tracker:
    """Tracks a camera (scene mode) or an object (object mode) from RGB frames.

    ``Tracker(config, backend)``: ``config`` is a ``TrackerConfig`` (or a dict of its fields, or
    None for defaults); ``backend`` implements ``kvtracker_sdk.backends.base.Backend``. The tracker
    does not close a backend it was given; it closes one it created (``from_pretrained``).
    Callbacks (``events.on_*``) run on the thread that called the method causing them (see
    ``core/events.py``). ``camera``: the input images' intrinsics for the session (the
    ``camera`` property changes them; ``push_frame(camera=...)`` overrides them for one frame);
    distorted frames are undistorted. ``segmenter``: object mode's ``Segmenter`` (optional; see
    ``object.set_segmenter``).

    Members by group: frames in (``push_frame``, ``submit``); the session (``initialize``,
    ``reset``, ``close``, ``set_backend``, ``camera``); reading (``snapshot``, ``state``,
    ``reason``, ``get_pose``, ``get_tracked_pose``, ``keyframe_map``, ``map_status``, ``config``,
    ``backend``); maps (``from_map``, ``save_map``, ``wait_for_map``); and the views ``events``,
    ``live``, ``object``, ``world``, ``export``.
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
        self._last_timestamp: float | None = None  # of the session's last frame: time order
        self._closed = False
        self._camera = check_camera(camera)
        crops = cfg.mode is TrackingMode.OBJECT and (
            cfg.object.preprocessing is ObjectPreprocessing.CROP
        )
        self._intrinsics = FrameIntrinsics(estimate=not crops)  # per-frame crops: no map-wide fit
        self._last_intrinsics: tuple[Camera, IntrinsicsSource] | None = None
        self._intake: LiveIntake | None = None  # made by the first submit()
        self._intake_lock = threading.Lock()  # never the tracker's lock: submit must not wait
        self._object_mode = cfg.mode is TrackingMode.OBJECT
        self._mode: FrameMode = SceneFrames(checked_segmenter(segmenter))
        if self._object_mode:  # the object's region before and after each step
            regions = RegionPropagator(margin=cfg.object.crop_margin_px,
                                       models=self._keeper.objects)
            self._mode = ObjectFrames(regions, self._mode.segmenter,
                                      search_frames=cfg.object.search_frames)
        self._depth_undistort = Undistorter()  # depth follows its colour frame's undistortion

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
        WARNING ``map_camera_mismatch`` is logged (``persistence.load_tracker_map``)."""
        loaded = persistence.load_tracker_map(
            path, backend.info, config, backend_preprocessing=family_preprocessing(
                backend.info.family, getattr(backend, "preprocessing", None)).name, camera=camera)
        tracker = cls(loaded.config, backend, camera=camera)
        tracker._install_loaded_map(loaded.keyframe_map, rebuild=rebuild)
        return tracker

    # ------------------------------------------------------------------ read-only views
    @property
    def config(self) -> TrackerConfig:
        """The configuration in use (an unset resolution resolved to the family's default)."""
        return self._config

    @property
    def backend(self) -> Backend:
        """The backend running the network now (``set_backend`` swaps it)."""
        return self._loop.backend

    @property
    def state(self) -> TrackingState:
        """The tracking state; read it with ``reason`` at once through ``snapshot()``."""
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
        """The map's size and health, its world (metric? gravity-aligned?) and each scale
        source's estimate with its uncertainty (``kvtracker_sdk.world``)."""
        aligner = self._loop.aligner
        return replace(self._keeper.status(), failed_tracks=self._loop.failed_tracks,
                       scale_estimates=aligner.estimates(),
                       gravity=aligner.gravity_estimate(self._keeper.map))

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
        """The session's given intrinsics (None: predicted or estimated per frame). Assign a
        ``Camera`` (or None, to forget them) to change them from the next frame on; InputError
        for anything else."""
        return self._camera

    @camera.setter
    def camera(self, camera: Camera | None) -> None:
        checked = check_camera(camera)
        with self._call():
            self._camera = checked

    # ------------------------------------------------------------------ the grouped members
    # Each view is made on access: it holds the tracker, and the tracker holds no view, so no
    # reference cycle keeps a dropped tracker (and its map) alive until the garbage collector runs.
    @property
    def events(self) -> TrackerEvents:
        """Callback registration: ``on_state_change``, ``on_keyframe``, ... and ``unregister``
        (``tracker_events``)."""
        return TrackerEvents(self._events)

    @property
    def live(self) -> TrackerLive:
        """The live intake's ``latest()``, ``stats`` and ``wait_idle()`` (``tracker_live``)."""
        return TrackerLive(self)

    @property
    def object(self) -> TrackerObject:
        """Object mode's ``frame``, ``region`` and ``set_segmenter()`` (``tracker_object``)."""
        return TrackerObject(self)

    @property
    def world(self) -> TrackerWorld:
        """Known sizes that make the world metric: ``set_known_distance()``,
        ``set_object_height()`` (``tracker_world``)."""
        return TrackerWorld(self)

    @property
    def export(self) -> TrackerExport:
        """The map as files: ``point_cloud()``, ``trajectory()`` (``tracker_export``)."""
        return TrackerExport(self)

    if not TYPE_CHECKING:  # hidden from type checkers: an old name in the SDK is a type error

        def __getattr__(self, name: str) -> Any:
            """Only for names the class lacks: the renamed members' old spellings, with a
            ``DeprecationWarning`` (``tracker_renames``)."""
            return renamed_member(self, name)

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
            backend_preprocessing=self._preparer.preprocessing.name, camera=self._camera)
        self._install_loaded_map(loaded.keyframe_map, rebuild=rebuild)

    def reset(self) -> None:
        """Drop the map (a pending rebuild is discarded) and return to INIT with reason RESET."""
        with self._call():
            self._loop.drop_map(_R.RESET)
            self._input_size = None
            self._last_timestamp = None
            self._mode.reset()
            self._loop.fire(TrackingEvent.RESET, None)

    def _install_loaded_map(self, kf_map: KeyframeMap, *, rebuild: bool = False) -> None:
        """Persistence seam: install a saved map and relocalise against it (RELOCALIZING,
        MAP_LOADED). The caller has checked the map's model fingerprint."""
        with self._call():
            if kf_map.cache.layout != self.backend.info.layout:
                raise BackendMismatchError(
                    f"map cache layout {kf_map.cache.layout} != backend {self.backend.info.layout}"
                )
            self._input_size = None
            self._last_timestamp = None
            self._mode.reset()
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

    def __exit__(self, *exc_info: Any) -> None:  # Any: in this class "object" is the view
        self.close()

    # ------------------------------------------------------------------ live intake
    def submit(
        self, image: np.ndarray, timestamp: float | None = None, *, mask: np.ndarray | None = None,
        bbox: Any = None, camera: Camera | None = None, captured_at: float | None = None,
        color: str = "rgb",
        depth: np.ndarray | None = None, depth_scale: float | None = None,
        gravity: Any = None,
    ) -> None:
        """Hand a frame to the live worker and return at once (``tracking/live/live_intake.py``).

        The frame as in ``push_frame`` (HxWx3 uint8 RGB; ``color="bgr"`` for OpenCV frames).

        The worker always tracks the newest frame; one still waiting when a newer arrives is
        dropped and counted. Results: ``events.on_result`` callbacks and ``live.latest()``; counters
        and latency: ``live.stats``. ``timestamp`` defaults to the wall-clock time now (capture
        time).
        For live use, build the tracker with ``threading={"async_mapping": True}`` so that
        rebuilds do not pause tracking. ``depth``, ``depth_scale``, ``gravity``: as in
        ``push_frame`` (a depth frame or gravity reading travels with its colour frame).
        """
        self._live().submit(image, timestamp, mask=mask, bbox=bbox, camera=camera,
                            captured_at=captured_at, color=color, depth=depth,
                            depth_scale=depth_scale, gravity=gravity)

    def _live(self) -> LiveIntake:
        intake = self._intake
        if intake is None:
            with self._intake_lock:
                if self._closed:
                    raise StateError("the tracker is closed")
                if self._intake is None:
                    self._intake = LiveIntake(self.push_frame, events=self._events)
                intake = self._intake
        return intake

    # ------------------------------------------------------------------ the frame loop
    def push_frame(
        self, image: np.ndarray, timestamp: float | None = None, mask: np.ndarray | None = None,
        bbox: Any = None, camera: Camera | None = None, *, color: str = "rgb",
        depth: np.ndarray | None = None, depth_scale: float | None = None, gravity: Any = None,
    ) -> FrameResult:
        """Track one frame: an HxWx3 array, uint8 (or float in [0, 1]), RGB channel order.

        ``color="bgr"`` takes OpenCV's order (``cv2.imread``, ``cv2.VideoCapture.read``); a BGR
        frame passed as RGB is not detected, it tracks worse. ``timestamp``: seconds on any clock
        (reported unchanged); within a session stamps must not go backwards (``InputError``;
        ``reset()`` and a loaded map start a new session). ``camera``: this frame's intrinsics
        (else the session's); the result's ``intrinsics`` are the input image's: given,
        predicted or estimated (``tracking/core/intrinsics.py``).

        Object mode (``tracking/object/frame_mode.py``): ``mask`` (bool/int [H, W]) or ``bbox``
        (x0, y0, x1, y1) select the object, required with the first frame, optional afterwards
        (the region predicted from the map, or the ``Segmenter``'s mask, is used; the result's
        ``region`` and ``T_cam_object`` say where the object is); against a loaded object map
        not needed at all (the whole frame is searched; reason ``OBJECT_NOT_FOUND`` after
        ``object.search_frames`` frames in vain).

        ``depth``: a depth image registered to ``image`` (same H, W; float metres, or integer
        units with ``depth_scale`` metres per unit; 0 = none): keyframes with depth make the world
        metric (``tracking/world/world_alignment.py``). ``gravity``: gravity's direction in this
        frame's camera (3 numbers, OpenCV axes, pointing *down*, any length: a level camera reads
        about (0, 9.81, 0); pass an accelerometer's reading negated); readings turn the world's z
        axis up. Either may come with some frames only (gravity once is enough to level).

        The result's ``pose`` is None without a map (INIT, MAPPING) or when the backend failed on
        this frame (``error``); ``pose_valid`` is False while relocalising or for a low-confidence
        frame; ``keyframe_id`` is set when the frame became a keyframe in this call (synchronous
        mapping; else the ``events.on_keyframe`` event reports it later). Bad input raises an
        ``InputError`` subclass before anything changes; backend failures never raise.
        """
        start = time.perf_counter()
        with self._call():
            result = self._track(
                image, start, timestamp=timestamp, mask=mask, bbox=bbox, camera=camera,
                color=color, depth=depth, depth_scale=depth_scale, gravity=gravity)
        _log.debug("frame", frame_index=result.frame_index, state=result.state.value,
                   pose_valid=result.pose_valid, confidence=result.confidence,
                   **{f"{k}_ms": round(v, 3) for k, v in result.timings_ms.items()})
        return result

    def _track(
        self, image: Any, start: float, *, camera: Camera | None, **pushed: Any
    ) -> FrameResult:
        """Under the lock: everything pushed with the frame checked once (``check_frame``: a
        typed InputError before anything changes), then the frame through its mode's region
        (before the step), the model's input, the frame loop's step and the mode's observation
        (after it), to its result. ``start``: when ``push_frame`` was called."""
        frame = check_frame(
            image, min_side=self._preparer.patch_size,
            camera=self._camera if camera is None else camera,
            session_size=self._input_size, previous_timestamp=self._last_timestamp, **pushed)
        index, kf_map = self._frames, self._keeper.map
        regions_in = self._mode.before_step(frame, index, kf_map, start=time.perf_counter())
        prepared = self._preparer.to_model(
            frame, regions_in.mask, map_resolution=None if kf_map is None else kf_map.resolution,
            map_preprocessing=None if kf_map is None else kf_map.preprocessing)
        timings = {"preprocess": _ms(start) - regions_in.prompt_ms}
        if regions_in.segmented is not None:
            timings["segment"] = regions_in.prompt_ms
        self._loop.predicted_K = None  # set by this step if the network predicts intrinsics
        world_changes = self._loop.world_changes
        step = self._loop.step(prepared, index, timings, frame.gravity,
                               keyframe_allowed=not regions_in.searching)
        if self._loop.world_changes != world_changes:
            self._mode.forget_poses()  # extrapolating across worlds would mix them
        intrinsics, source = self._intrinsics.resolve(prepared, self._loop.predicted_K,
                                                      self._keeper.map)
        if intrinsics is not None and source is not None:
            self._last_intrinsics = (intrinsics, source)
        pose = step.pose.T_world_cam if step.valid and step.pose is not None else None
        seen = self._mode.after_step(regions_in, frame, index, self._keeper.map, pose,
                                     intrinsics, timings)
        if seen.search_exhausted and self.state is _S.RELOCALIZING:  # the app must point at it
            self._loop.fire(TrackingEvent.OBJECT_NOT_FOUND, index)
            _log.warning("the loaded map's object was not found in the whole frame",
                         frames=self._config.object.search_frames, hint=OBJECT_NOT_FOUND_HINT)
        # counted once it went through: an unexpected error leaves the session as it was
        self._frames, self._input_size = index + 1, frame.size
        if frame.timestamp is not None:
            self._last_timestamp = frame.timestamp
        timings["total"] = _ms(start)
        return FrameResult(
            frame_index=index, timestamp=frame.timestamp, state=self.state,
            reason=self.reason, pose=step.pose, pose_valid=step.valid,
            confidence=step.confidence, keyframe_id=step.keyframe_id,
            map_generation=self._loop.snapshot.map_generation, timings_ms=timings,
            extras={"rebuilding": self._keeper.rebuilding}, error=step.error,
            intrinsics=intrinsics, intrinsics_source=source, region=seen.region,
            T_cam_object=seen.T_cam_object, object_frame=seen.object_frame,
        )

    # ------------------------------------------------------------------ plumbing
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

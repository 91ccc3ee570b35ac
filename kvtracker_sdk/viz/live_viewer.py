"""``Viewer``: a live 3D view of a tracking session in the browser, served by viser.

Why viser (the ``[view]`` extra): a pure-Python server with a prebuilt web client inside its
wheel, made for live 3D scenes with a GUI panel; it binds the host it is given (here always
127.0.0.1), has no telemetry and fetches nothing at run time. rerun's web viewer would also do,
but serves a large wasm client, its SDK reports analytics unless switched off, and a second
rerun stream beside the ``.rrd`` recording would mix two uses of one library.

The page shows, while tracking (world frame = the tracker's, OpenCV axes, drawn with -y up):

- ``/camera``: the current camera's frustum with the current frame on it;
- ``/trajectory``: the line through the valid camera centres;
- ``/keyframes/kf_XXXX``: every keyframe's frustum (re-placed when a rebuild corrects the map);
- ``/points``: the map's fused point cloud;
- object mode: ``/object``, the object frame (``ObjectFrame``: its centre, keyframe 0's axes),
  and ``/object/region``, the object's extent (the oriented box of its fused points); the current
  frame in the panel is darkened outside its mask (the frame's region when none is given);
- a panel: state and reason, frames, FPS, keyframe frustums, map points (plain text, so a test
  or a person reads the same), and the current frame.

``Viewer(port=8080)`` starts serving at once (``url``); ``attach(tracker)`` follows state changes
and map updates; ``log_frame(image, result)`` after every ``push_frame``. Everything is thread
safe. ``close()`` stops the server.
"""

from __future__ import annotations

import collections
import contextlib
import io
import threading
import time
from types import TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np

from kvtracker_sdk.errors import ConfigError, MissingDependencyError
from kvtracker_sdk.geometry.se3 import quat_wxyz_from_rotation
from kvtracker_sdk.io.exports.intrinsics import DEFAULT_FOCAL_PER_WIDTH, estimate_intrinsics
from kvtracker_sdk.io.exports.map_export import fused_point_cloud
from kvtracker_sdk.tracking.object.object_model import ObjectModel
from kvtracker_sdk.types import FrameResult

if TYPE_CHECKING:
    from kvtracker_sdk.cache.keyframe_map import KeyframeMap
    from kvtracker_sdk.tracking.core.events import StateChangeEvent, Subscription
    from kvtracker_sdk.tracking.facade.tracker import Tracker

__all__ = ["LOOPBACK", "Viewer"]

LOOPBACK = "127.0.0.1"  # the only address the viewer binds: a live camera feed stays local
_TRAJECTORY_EVERY = 5  # frames between re-sends of the trajectory line
_TRAJECTORY_POINTS = 2000  # at most this many centres per send (the line is re-sent whole)


def _viser() -> Any:
    try:
        import viser
    except ImportError as exc:
        raise MissingDependencyError.for_extra("view", "the live view needs viser") from exc
    return viser


class Viewer:
    """Serves the live view on http://127.0.0.1:``port`` (0: a free port; see ``url``)."""

    def __init__(
        self,
        *,
        port: int = 8080,
        image_max_side: int = 240,
        max_points: int = 50_000,
        min_confidence: float = 0.5,
        title: str = "kvtracker",
    ) -> None:
        # checked before serving: viser retries port after port past 65535 and never returns
        if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
            raise ConfigError(f"port must be a whole number in 0..65535 (0: any free), got {port!r:.40}")
        viser = _viser()
        self.image_max_side, self.max_points = int(image_max_side), int(max_points)
        self.min_confidence = float(min_confidence)
        self._lock = threading.RLock()
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints a banner; the SDK doesn't
            self._server = viser.ViserServer(host=LOOPBACK, port=int(port), verbose=False)
        self._server.scene.set_up_direction("-y")  # OpenCV world: y points down
        self._title = title
        self._camera: Any = None
        self._keyframes: dict[int, Any] = {}
        self._centres: list[np.ndarray] = []
        self._fov_per_height: tuple[float, float] | None = None  # (vertical fov, aspect)
        self._state, self._reason = "INIT", "NONE"
        self.frames, self.num_points = 0, 0
        self._frame_times: collections.deque[float] = collections.deque(maxlen=30)
        self._closed = False
        self._panel = self._server.gui.add_markdown(self._panel_text())
        self._image = self._server.gui.add_image(np.zeros((2, 2, 3), np.uint8), label="frame")

    @property
    def url(self) -> str:
        return f"http://{LOOPBACK}:{self._server.get_port()}"

    @property
    def port(self) -> int:
        return int(self._server.get_port())

    @property
    def num_keyframes(self) -> int:
        return len(self._keyframes)

    # ------------------------------------------------------------------ wiring
    def attach(self, tracker: Tracker) -> list[Subscription]:
        """Follow ``tracker``'s state changes and map updates (and show its current map)."""
        self.log_map(tracker.keyframe_map)
        return [
            tracker.events.on_state_change(self.log_state_change),
            tracker.events.on_map_updated(lambda _event: self.log_map(tracker.keyframe_map)),
        ]

    # ------------------------------------------------------------------ updates
    def log_state_change(self, event: StateChangeEvent) -> None:
        with self._lock:
            self._state, self._reason = event.state.value, event.reason.value
            self._panel.content = self._panel_text()

    def log_frame(
        self, image: np.ndarray, result: FrameResult, *, mask: np.ndarray | None = None
    ) -> None:
        """The pushed frame [H, W, 3] uint8 RGB, its result, and (object mode) its mask (default:
        the result's region)."""
        if mask is None and result.region is not None:
            mask = result.region.mask
        thumb = _thumbnail(image, self.image_max_side)
        if mask is not None:
            small = _thumbnail(mask.astype(np.uint8) * 255, self.image_max_side) > 127
            thumb = np.where(small[..., None], thumb, (thumb * 0.35).astype(np.uint8))
        with self._lock:
            self.frames += 1
            self._frame_times.append(time.perf_counter())
            self._state, self._reason = result.state.value, result.reason.value
            self._image.image = thumb
            if result.pose_valid and result.pose is not None:
                self._place_camera(result.pose.T_world_cam, thumb)
            self._panel.content = self._panel_text()

    def log_map(self, keyframe_map: KeyframeMap | None) -> None:
        """Keyframe frustums and the fused cloud (and, in object mode, the object's region)."""
        if keyframe_map is None or not keyframe_map.keyframes:
            return
        points, colors, _ = fused_point_cloud(keyframe_map, min_confidence=self.min_confidence)
        if len(points) > self.max_points:
            keep = np.random.default_rng(0).choice(len(points), self.max_points, replace=False)
            points, colors = points[keep], colors[keep]
        object_mode = any(kf.mask is not None for kf in keyframe_map.keyframes)
        scene = self._server.scene
        with self._lock:
            if self._fov_per_height is None:
                first = keyframe_map.keyframes[0]
                camera = estimate_intrinsics(first.local_points, first.confidence_map)
                self._fov_per_height = (camera.vertical_fov, camera.width / camera.height)
                self._look_at(first.T_world_cam, points)
            for gone in set(self._keyframes) - set(keyframe_map.keyframe_ids):
                self._keyframes.pop(gone).remove()
            size = _frustum_size(points)
            for kf in keyframe_map.keyframes:
                wxyz, position = _pose(kf.T_world_cam)
                handle = self._keyframes.get(kf.keyframe_id)
                if handle is None:
                    fov, aspect = self._fov_per_height
                    self._keyframes[kf.keyframe_id] = scene.add_camera_frustum(
                        f"/keyframes/kf_{kf.keyframe_id:04d}", fov=fov, aspect=aspect,
                        scale=size, image=_thumbnail(kf.image, 96), color=(40, 140, 255),
                        wxyz=wxyz, position=position, thickness=2.0, thickness_units="screen")
                else:
                    handle.wxyz, handle.position = wxyz, position
            if len(points):
                scene.add_point_cloud("/points", points.astype(np.float32), colors,
                                      point_size=size * 0.02)
            model = ObjectModel.of(keyframe_map) if object_mode else None
            if model is not None:
                # the object frame (centre, keyframe 0's axes) and its extent, in object axes
                wxyz, position = _pose(model.frame.T_world_object)
                scene.add_frame("/object", axes_length=size, axes_radius=size * 0.03,
                                wxyz=wxyz, position=position)
                extent = model.frame.extent
                box_wxyz, box_position = _pose(extent.T_ref_box)
                scene.add_box("/object/region", color=(255, 180, 0),
                              dimensions=tuple(float(v) for v in extent.size), wxyz=box_wxyz,
                              position=box_position, wireframe=True)
            self.num_points = len(points)
            self._panel.content = self._panel_text()

    # ------------------------------------------------------------------ closing
    def close(self) -> None:
        """Stop serving. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        # viser prints one line when its server thread stops; the SDK prints nothing
        with contextlib.redirect_stdout(io.StringIO()):
            self._server.stop()

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.close()

    # ------------------------------------------------------------------ helpers
    def _place_camera(self, T_world_cam: np.ndarray, thumb: np.ndarray) -> None:
        wxyz, position = _pose(T_world_cam)
        self._centres.append(position)
        scene = self._server.scene
        if self._camera is None:
            fov, aspect = self._fov_per_height or (
                2 * np.arctan(0.5 / DEFAULT_FOCAL_PER_WIDTH * thumb.shape[0] / thumb.shape[1]),
                thumb.shape[1] / thumb.shape[0])
            self._camera = scene.add_camera_frustum(
                "/camera", fov=fov, aspect=aspect, scale=0.1, image=thumb, color=(255, 60, 60),
                wxyz=wxyz, position=position, thickness=2.0, thickness_units="screen")
        else:
            self._camera.wxyz, self._camera.position, self._camera.image = wxyz, position, thumb
        if len(self._centres) >= 2 and len(self._centres) % _TRAJECTORY_EVERY in (0, 2):
            centres = np.asarray(self._centres, dtype=np.float32)
            if len(centres) > _TRAJECTORY_POINTS:  # a long run: evenly thinned, ends kept
                keep = np.linspace(0, len(centres) - 1, _TRAJECTORY_POINTS).round().astype(int)
                centres = centres[keep]
            segments = np.stack([centres[:-1], centres[1:]], axis=1)  # [S, 2, 3]
            scene.add_line_segments("/trajectory", segments, colors=(255, 60, 60),
                                    thickness=2.0, thickness_units="screen")

    def _look_at(self, T_world_cam: np.ndarray, points: np.ndarray) -> None:
        """New pages start behind and above the first keyframe, looking at the cloud."""
        target = np.median(points, axis=0) if len(points) else T_world_cam[:3, 3]
        centre = T_world_cam[:3, 3]
        distance = float(np.linalg.norm(target - centre)) or 1.0
        back, up = -T_world_cam[:3, 2], -T_world_cam[:3, 1]  # OpenCV: z forward, y down
        camera = self._server.initial_camera
        camera.position = centre + distance * (1.5 * back + 1.0 * up)
        camera.look_at = target
        camera.up = up

    def _panel_text(self) -> str:
        times = self._frame_times  # FPS over the last 30 frames
        span = times[-1] - times[0] if len(times) > 1 else 0.0
        fps = (len(times) - 1) / span if span > 0 else 0.0
        return (
            f"**{self._title}**\n\n"
            f"state: {self._state} ({self._reason})\n\n"
            f"frames: {self.frames}\n\n"
            f"fps: {fps:.1f}\n\n"
            f"keyframe frustums: {len(self._keyframes)}\n\n"
            f"map points: {self.num_points}"
        )


def _pose(T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz quaternion, position) of a camera-to-world pose, as viser places a node."""
    return quat_wxyz_from_rotation(T_world_cam[:3, :3]), np.array(T_world_cam[:3, 3], np.float64)


def _frustum_size(points: np.ndarray) -> float:
    """A frustum size suited to the scene: 5 % of the cloud's extent (0.1 without points)."""
    if len(points) < 2:
        return 0.1
    low, high = np.percentile(points, [5, 95], axis=0)
    extent = float(np.linalg.norm(high - low))
    return 0.05 * extent if np.isfinite(extent) and extent > 0 else 0.1


def _thumbnail(image: np.ndarray, max_side: int) -> np.ndarray:
    import cv2

    height, width = image.shape[:2]
    factor = max_side / max(height, width)
    if factor >= 1.0:
        return np.ascontiguousarray(image)
    size = (max(1, round(width * factor)), max(1, round(height * factor)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)

"""``RerunSink``: record a tracking session as a rerun ``.rrd`` file (frames, camera, map, states).

It never logs through rerun's global recording and never spawns a viewer: it owns one
``rr.RecordingStream`` whose only sink is a file, so embedding the SDK next to an app's own rerun
logging cannot mix the two. The file is written beside its target and moved into place by
``close()`` (a run that fails leaves no half-written recording). Open it with ``rerun FILE.rrd``.

Entities (world frame = the tracker's, OpenCV axes: x right, y down, z forward, logged as RDF):

- ``world/camera``: the current ``T_world_cam`` (valid poses only) with a pinhole frustum, and
  ``world/camera/image``, the pushed frame (downscaled, JPEG);
- ``world/keyframes/kf_XXXX``: every keyframe's pose and frustum with its model-resolution image,
  re-logged when a rebuild corrects the map, cleared when a keyframe is evicted;
- ``world/points``: the map's fused, confidence-filtered point cloud after every map update;
- ``world/trajectory``: the line through the valid camera centres;
- ``tracking/confidence`` (scalar per frame) and ``tracking/state`` (a text log of transitions).

Timelines: ``frame`` (the frame index) and ``time`` (the frame's timestamp, seconds).
The focal length the frustums use is estimated from the model's local points of keyframe 0
(the model predicts geometry, not intrinsics), in pixels per image width.
"""

from __future__ import annotations

import os
from pathlib import Path
from types import ModuleType, TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np

from kvtracker_sdk.errors import MissingDependencyError
from kvtracker_sdk.io.exports.map_export import fused_point_cloud
from kvtracker_sdk.io.files.atomic import atomic_path
from kvtracker_sdk.types import FrameResult

if TYPE_CHECKING:
    from kvtracker_sdk.cache.keyframe_map import Keyframe, KeyframeMap
    from kvtracker_sdk.tracking.core.events import StateChangeEvent, Subscription
    from kvtracker_sdk.tracking.facade.tracker import Tracker

__all__ = ["RerunSink"]

_TRAJECTORY_EVERY = 30  # frames between re-logs of the trajectory line (its cost grows with it)


class _Discarded(Exception):
    """Ends the temporary file's ``atomic_path`` block so that the file is removed."""


def _rerun() -> ModuleType:
    try:
        import rerun
    except ImportError as exc:
        raise MissingDependencyError.for_extra("viz", "recording to rerun needs rerun-sdk") from exc
    return rerun


class RerunSink:
    """Logs frames, poses, keyframes and the point cloud of a session into ``path`` (``.rrd``).

    ``image_max_side`` caps the logged frames' longer side (pixels); ``max_points`` caps the
    logged cloud (a seeded random subset); ``min_confidence`` filters it like the PLY export.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        application_id: str = "kvtracker",
        image_max_side: int = 320,
        jpeg_quality: int = 80,
        max_points: int = 50_000,
        min_confidence: float = 0.5,
    ) -> None:
        self._rr = _rerun()
        self.path = Path(path)
        self.image_max_side = int(image_max_side)
        self.jpeg_quality = int(jpeg_quality)
        self.max_points = int(max_points)
        self.min_confidence = float(min_confidence)
        # atomic_path moves the file into place when its block ends cleanly and deletes it when
        # the block raises: the block spans the sink's life, from here to close()
        self._file = atomic_path(self.path)
        tmp = self._file.__enter__()
        try:
            self._rec = self._rr.RecordingStream(application_id)  # not the global recording
            self._rec.save(tmp)
            self._rec.log("world", self._rr.ViewCoordinates.RDF, static=True)
        except BaseException as exc:
            self._file.__exit__(type(exc), exc, exc.__traceback__)  # removes the temporary file
            raise
        self._focal_per_width: float | None = None
        self._frustum: tuple[float | None, int, int] | None = None  # last logged camera frustum
        self._keyframe_ids: set[int] = set()
        self._centres: list[np.ndarray] = []
        self._closed = False

    # ------------------------------------------------------------------ wiring
    def attach(self, tracker: Tracker) -> list[Subscription]:
        """Log ``tracker``'s state changes and map updates as they happen."""
        return [
            tracker.events.on_state_change(self.log_state_change),
            tracker.events.on_map_updated(lambda _event: self.log_map(tracker.keyframe_map)),
        ]

    def set_time(self, frame_index: int, timestamp: float | None) -> None:
        """Place what is logged next on the ``frame`` (and ``time``) timelines."""
        self._rec.set_time("frame", sequence=int(frame_index))
        if timestamp is not None:
            self._rec.set_time("time", duration=float(timestamp))

    # ------------------------------------------------------------------ logging
    def log_frame(self, image: np.ndarray, result: FrameResult) -> None:
        """The pushed frame [H, W, 3] uint8 RGB, its pose (if valid) and its confidence."""
        rr = self._rr
        thumb = self._thumbnail(image)
        self._rec.log("world/camera/image", self._encoded(thumb))
        if result.confidence is not None:
            self._rec.log("tracking/confidence", rr.Scalars(float(result.confidence)))
        if not (result.pose_valid and result.pose is not None):
            return
        pose = result.pose.T_world_cam
        self._rec.log("world/camera", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        frustum = (self._focal_per_width, thumb.shape[1], thumb.shape[0])
        if self._focal_per_width is not None and frustum != self._frustum:  # log on change only
            self._rec.log("world/camera", self._pinhole(thumb.shape[1], thumb.shape[0]))
            self._frustum = frustum
        self._centres.append(pose[:3, 3].copy())
        if len(self._centres) % _TRAJECTORY_EVERY == 1:
            self._log_trajectory()

    def log_state_change(self, event: StateChangeEvent) -> None:
        text = f"{event.previous.value} -> {event.state.value} ({event.reason.value})"
        level = "WARN" if event.state.value == "RELOCALIZING" else "INFO"
        self._rec.log("tracking/state", self._rr.TextLog(text, level=level))

    def log_map(self, keyframe_map: KeyframeMap | None) -> None:
        """Keyframe poses and frustums (new keyframes with their image) and the fused cloud."""
        if keyframe_map is None:
            return
        rr = self._rr
        if self._focal_per_width is None:
            self._focal_per_width = _focal_per_width(keyframe_map.keyframes[0])
        current = set(keyframe_map.keyframe_ids)
        for gone in self._keyframe_ids - current:
            self._rec.log(f"world/keyframes/kf_{gone:04d}", rr.Clear(recursive=True))
        for kf in keyframe_map.keyframes:
            entity = f"world/keyframes/kf_{kf.keyframe_id:04d}"
            T = kf.T_world_cam
            self._rec.log(entity, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
            if kf.keyframe_id not in self._keyframe_ids:
                height, width = kf.image.shape[:2]
                self._rec.log(entity, self._pinhole(width, height, plane=0.1))
                self._rec.log(f"{entity}/image", self._encoded(kf.image))
        self._keyframe_ids = current
        points, colors, _ = fused_point_cloud(keyframe_map, min_confidence=self.min_confidence)
        if len(points) > self.max_points:
            keep = np.random.default_rng(0).choice(len(points), self.max_points, replace=False)
            points, colors = points[keep], colors[keep]
        self._rec.log("world/points", rr.Points3D(points.astype(np.float32), colors=colors))

    # ------------------------------------------------------------------ closing
    def close(self, *, keep: bool = True) -> None:
        """Finish the file and move it into place (``keep=False`` discards it). Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            if keep and self._centres:
                self._log_trajectory()
            self._rec.flush()
            self._rec.disconnect()  # closes the file sink (writes its footer)
        except BaseException as exc:
            self._file.__exit__(type(exc), exc, exc.__traceback__)
            raise
        if keep:
            self._file.__exit__(None, None, None)
        else:
            discarded = _Discarded(str(self.path))
            self._file.__exit__(_Discarded, discarded, None)

    def __enter__(self) -> RerunSink:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        self.close(keep=error is None)

    # ------------------------------------------------------------------ helpers
    def _log_trajectory(self) -> None:
        strip = np.asarray(self._centres, dtype=np.float32)
        self._rec.log("world/trajectory", self._rr.LineStrips3D([strip]))

    def _pinhole(self, width: int, height: int, *, plane: float | None = None) -> Any:
        focal = float(self._focal_per_width or 1.0) * width
        return self._rr.Pinhole(
            focal_length=focal,
            resolution=[width, height],
            camera_xyz=self._rr.ViewCoordinates.RDF,
            image_plane_distance=plane,
        )

    def _thumbnail(self, image: np.ndarray) -> np.ndarray:
        import cv2

        height, width = image.shape[:2]
        factor = self.image_max_side / max(height, width)
        if factor >= 1.0:
            return image
        size = (max(1, round(width * factor)), max(1, round(height * factor)))
        return cv2.resize(image, size, interpolation=cv2.INTER_AREA)

    def _encoded(self, image: np.ndarray) -> Any:
        """uint8 RGB [H, W, 3] as a JPEG blob (OpenCV encodes: no Pillow needed)."""
        import cv2

        rgb = image if image.dtype == np.uint8 else np.clip(image * 255.0, 0, 255).astype(np.uint8)
        ok, data = cv2.imencode(
            ".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality]
        )
        if not ok:  # pragma: no cover - OpenCV always encodes a valid uint8 image
            raise RuntimeError("JPEG encoding failed")
        return self._rr.EncodedImage(contents=data.tobytes(), media_type="image/jpeg")


def _focal_per_width(keyframe: Keyframe, min_confidence: float = 0.5) -> float:
    """Least-squares focal length / image width from the keyframe's local points.

    A pixel (u, v) sees the camera-frame point (x, y, z) at u - cx = f x / z, v - cy = f y / z
    (principal point at the image centre); f minimises the squared residuals over the confident
    pixels. Falls back to 0.8 (a ~64 degree horizontal field of view) without usable points.
    """
    points = keyframe.local_points.astype(np.float64)
    height, width = points.shape[:2]
    v, u = np.mgrid[0:height, 0:width]
    offsets = np.stack([u + 0.5 - width / 2.0, v + 0.5 - height / 2.0], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        rays = points[..., :2] / points[..., 2:3]
    usable = (keyframe.confidence_map >= min_confidence) & (points[..., 2] > 0)
    usable &= np.all(np.isfinite(rays), axis=-1)
    a, b = rays[usable], offsets[usable]
    denominator = float(np.sum(a * a))
    focal = float(np.sum(a * b)) / denominator if denominator > 0 else 0.0
    return focal / width if focal > 0 else 0.8

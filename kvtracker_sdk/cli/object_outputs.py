"""``object.json``: what an object-mode run knows about the object, for anchoring content later.

* ``object_frame``: ``T_world_object`` (origin at the object centre; z along ``up``, the support
  plane's normal, for an object standing on one, else the axes of keyframe 0) and the extent (an
  oriented box of the fused object points: ``T_object_box``, ``half_extents``), in the map's
  units (monocular: no metric scale);
* ``object_frames``: every object frame a ``T_cam_object`` below refers to, by the
  ``map_generation`` it was fitted to (the object frame moves a little with each rebuild);
* ``frames``: per frame, the region (``source``: given / segmented / predicted / held; ``box`` and
  ``context_box`` in pixels, x1/y1 exclusive), ``T_cam_object`` (null without a valid pose) and
  ``object_frame``: the ``map_generation`` of the object frame ``T_cam_object`` refers to.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from kvtracker_sdk.types import FrameResult, ObjectFrame

if TYPE_CHECKING:
    from kvtracker_sdk.tracking.facade.tracker import Tracker

__all__ = ["object_document"]


def _frame(result: FrameResult) -> dict[str, Any]:
    region = result.region
    return {
        "frame_index": result.frame_index,
        "timestamp": result.timestamp,
        "source": None if region is None else region.source.value,
        "box": None if region is None else list(region.box),
        "context_box": None if region is None else list(region.context_box),
        "T_cam_object": None if result.T_cam_object is None else result.T_cam_object.tolist(),
        "object_frame": None if result.object_frame is None else result.object_frame.map_generation,
    }


def _anchor(frame: ObjectFrame) -> dict[str, Any]:
    return {
        "T_world_object": frame.T_world_object.tolist(),
        "extent": {"T_object_box": frame.extent.T_ref_box.tolist(),
                   "half_extents": frame.extent.half_extents.tolist()},
        "num_points": frame.num_points,
        "map_generation": frame.map_generation,
        "up": None if frame.up is None else frame.up.tolist(),
    }  # fmt: skip


def object_document(tracker: Tracker, results: list[FrameResult]) -> dict[str, Any]:
    """The JSON document of ``object.json`` (see the module docstring)."""
    frame = tracker.object.frame
    used = {r.object_frame.map_generation: r.object_frame for r in results
            if r.object_frame is not None}
    return {
        "convention": "T_world_object: origin at the object centre; z = up (the support plane's "
                      "normal) when up is set, else axes of keyframe 0 (OpenCV); a frame's "
                      "T_cam_object = inv(T_world_cam) @ T_world_object of the object frame its "
                      "'object_frame' names (a map_generation in object_frames); boxes "
                      "(x0, y0, x1, y1) in input pixels, x1/y1 exclusive",
        "object_frame": None if frame is None else _anchor(frame),  # of the final map
        "object_frames": {str(g): _anchor(f) for g, f in sorted(used.items())},
        "frames": [_frame(r) for r in results],
    }

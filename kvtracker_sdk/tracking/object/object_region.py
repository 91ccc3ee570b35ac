"""Region propagation: where the object is in each frame, from one mask or box.

The app gives the object once (a mask or a box with a frame; again whenever it likes). From then
on, each frame's region comes from the map: its fused object points (``object_model``) projected
with a pose and the input image's intrinsics (``FrameResult.intrinsics``: given, predicted by the
network or estimated from its points):

* **prompt** (before the frame is tracked): the pose extrapolated at constant velocity from the
  two previous frames' tracked poses. Its mask, grown by 15 % of its box (``grown_mask``), is
  what the frame is tracked with — object mode blacks the background outside it, or crops to its
  box grown by ``crop_margin_px`` — unless the app's ``Segmenter`` answers the prompt with a mask
  of its own (``tracking/object/segmenter.py``).
* **result** (``FrameResult.region``): the projection at the frame's own tracked pose
  (``PREDICTED``), the app's mask or box (``GIVEN``), or the segmenter's mask (``SEGMENTED``).
  Without a trusted pose (loss, relocalisation, no map yet) or when the object is out of view or
  the intrinsics are unknown, the last region is kept (``HELD``); once the tracker relocalises it
  is predicted again.
* **search** (a map loaded from a file, no pose yet): no region is known, so the frame is tracked
  unmasked — the whole frame is where the object can be — and may not become a keyframe; once
  the tracker relocalises, the region is predicted as above. ``object.search_frames`` frames
  without finding it set the reason ``OBJECT_NOT_FOUND`` (``OBJECT_NOT_FOUND_HINT``).

The region's mask is the projected points splatted on a grid whose cell matches their spacing,
closed and hole-filled (a silhouette, not a depth test: points on the far side of the object
fall inside it anyway); its box holds every projected point (clipped to the image).

Object mode (``frame_mode.ObjectFrames``) asks a ``RegionPropagator`` once before a frame's step
(``input_mask``) and once after it (``observe``), with the frame as checked on entry
(``FrameInput``).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.geometry.boxes import ImageBox, grow_box, mask_box
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.preprocess import box_mask
from kvtracker_sdk.tracking.core.frame_input import FrameInput
from kvtracker_sdk.tracking.object.object_model import ObjectModelCache
from kvtracker_sdk.tracking.object.segmenter import Segmenter, ask_segmenter
from kvtracker_sdk.types import ObjectFrame, ObjectRegion, RegionSource

__all__ = [
    "OBJECT_NOT_FOUND_HINT",
    "RegionPropagator",
    "grown_mask",
    "project_region",
    "projected_mask",
    "region_of_mask",
    "splat_mask",
]

OBJECT_NOT_FOUND_HINT = (
    "give the object's mask or box with a frame that shows it (push_frame(..., mask=...) or "
    "bbox=(x0, y0, x1, y1); CLI: --bbox x0,y0,x1,y1 --bbox-once, or --masks DIR)"
)

_MIN_POINTS = 8  # fewer projected points than this: the object is out of view
_MAX_CELL = 16
_GROWTH = 0.15  # a predicted mask grows by this fraction of its box's longer side to track with


def splat_mask(uv: np.ndarray, size: tuple[int, int], box: ImageBox) -> np.ndarray:
    """bool [H, W] silhouette of projected points ``uv`` [N, 2] (pixel centres at integers)
    inside ``box`` of an image of ``size``: points marked on a grid of cells sized to their mean
    spacing in the box, closed and hole-filled, then scaled back to pixels. Only the box's cells
    (and a border of one) are processed."""
    height, width = size
    area = max((box[2] - box[0]) * (box[3] - box[1]), 1.0)
    cell = int(min(_MAX_CELL, max(1, math.ceil(1.5 * math.sqrt(area / max(len(uv), 1))))))
    # grid cells covering the box, one cell of border: closing erodes at the grid's edges
    c0, r0 = int(box[0]) // cell - 1, int(box[1]) // cell - 1
    c1, r1 = math.ceil(box[2]) // cell + 2, math.ceil(box[3]) // cell + 2
    cols = np.floor((uv[:, 0] + 0.5) / cell).astype(np.int64) - c0
    rows = np.floor((uv[:, 1] + 0.5) / cell).astype(np.int64) - r0
    inside = (rows >= 0) & (rows < r1 - r0) & (cols >= 0) & (cols < c1 - c0)
    grid = np.zeros((r1 - r0, c1 - c0), dtype=bool)
    grid[rows[inside], cols[inside]] = True
    grid = ndimage.binary_fill_holes(ndimage.binary_closing(grid))
    mask = np.zeros(size, dtype=bool)
    pixels = np.repeat(np.repeat(grid, cell, axis=0), cell, axis=1)
    top, left = r0 * cell, c0 * cell  # may be negative: clip the window to the image
    y0, x0 = max(0, top), max(0, left)
    y1, x1 = min(height, top + pixels.shape[0]), min(width, left + pixels.shape[1])
    if y0 < y1 and x0 < x1:
        mask[y0:y1, x0:x1] = pixels[y0 - top : y1 - top, x0 - left : x1 - left]
    return mask


def grown_mask(region: ObjectRegion) -> np.ndarray:
    """bool [H, W]: ``region``'s mask dilated (square) by 15 % of its box's longer side (>= 2 px),
    clipped to its context box: the mask a frame is tracked with. The growth lets surface that
    comes into view enter the keyframes' masks (the foreground rule of ``object_model`` drops the
    background it also takes in)."""
    x0, y0, x1, y1 = region.box
    grow = max(2, math.ceil(_GROWTH * max(x1 - x0, y1 - y0)))
    mask = region.mask
    row0, col0, rows, cols = region.mask_window
    if not (rows and cols):
        return mask
    height, width = region.image_size
    r0, c0 = max(0, row0 - grow), max(0, col0 - grow)
    r1, c1 = min(height, row0 + rows + grow), min(width, col0 + cols + grow)
    mask[r0:r1, c0:c1] = ndimage.maximum_filter(mask[r0:r1, c0:c1], size=2 * grow + 1)
    cx0, cy0, cx1, cy1 = region.context_box
    context = np.zeros_like(mask)
    context[int(cy0) : math.ceil(cy1), int(cx0) : math.ceil(cx1)] = True
    return mask & context


def projected_mask(
    points: np.ndarray, T_world_cam: np.ndarray, camera: Camera
) -> tuple[np.ndarray, ImageBox] | None:
    """(bool [H, W] silhouette, box) of world ``points`` [N, 3] seen by a camera at
    ``T_world_cam`` with intrinsics ``camera`` (its image size is the mask's); None when fewer
    than 8 points lie in front of the camera and inside the image (the object is out of view)."""
    T_cam_world = np.linalg.inv(np.asarray(T_world_cam, dtype=np.float64))
    local = points @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    in_front = local[:, 2] > 1e-6 * max(float(np.abs(local[:, 2]).max(initial=0.0)), 1e-12)
    uv = camera.project(local[in_front])
    size = camera.size
    height, width = size
    visible = (
        (uv[:, 0] >= -0.5) & (uv[:, 0] < width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < height - 0.5)
    )
    if int(visible.sum()) < _MIN_POINTS:
        return None
    # all points count: stray ones were dropped by the foreground rule and the anchor ball, and
    # the rim of what the keyframes saw is thinly sampled (a trimmed box shrinks on that side)
    low = uv.min(axis=0) + 0.5  # pixel centres -> box coordinates
    high = uv.max(axis=0) + 0.5
    box = (max(0.0, float(low[0])), max(0.0, float(low[1])),
           min(float(width), float(high[0])), min(float(height), float(high[1])))
    if not (box[0] < box[2] and box[1] < box[3]):
        return None
    mask = splat_mask(uv[visible], size, box)
    if not mask.any():
        return None
    return mask, box


def region_of_mask(
    mask: np.ndarray, box: ImageBox | None, *, margin: float, frame_index: int,
    source: RegionSource,
) -> ObjectRegion:
    """The region over bool [H, W] ``mask``, which must select a pixel. ``box``: the app's box,
    or the projected points' (``projected_mask``); None: the mask's tight box. The region's
    context box is that box dilated by ``margin`` pixels, clipped to the image."""
    size = (int(mask.shape[0]), int(mask.shape[1]))
    tight = box if box is not None else mask_box(mask)
    assert tight is not None  # validated masks select a pixel
    context = grow_box(tight, margin, size)
    return ObjectRegion.from_mask(mask, box=tight, context_box=context, source=source,
                                  frame_index=frame_index)


def project_region(
    points: np.ndarray, T_world_cam: np.ndarray, camera: Camera, *, margin: float,
    frame_index: int, source: RegionSource = RegionSource.PREDICTED,
) -> ObjectRegion | None:
    """The region of world ``points`` [N, 3] seen by a camera at ``T_world_cam`` with intrinsics
    ``camera`` (``projected_mask``; None: the object is out of view)."""
    projected = projected_mask(points, T_world_cam, camera)
    if projected is None:
        return None
    mask, box = projected
    return region_of_mask(mask, box, margin=margin, frame_index=frame_index, source=source)


class RegionPropagator:
    """One tracker's object region over time (see the module docstring). Not thread-safe: the
    tracker's lock guards it."""

    def __init__(self, *, margin: float, models: ObjectModelCache | None = None) -> None:
        """``margin``: the context box's dilation (pixels); ``models``: the map's object models
        (the ``MapKeeper``'s, shared with the object keyframe rule)."""
        self.margin = float(margin)
        self.models = models if models is not None else ObjectModelCache()
        self.last: ObjectRegion | None = None
        self._poses: list[tuple[int, np.ndarray]] = []  # the last two valid (index, T_world_cam)
        self._camera: Camera | None = None  # the last frame's input intrinsics

    def reset(self) -> None:
        """Forget the region, poses and camera (a new session, maybe at another size)."""
        self.last, self._poses, self._camera = None, [], None

    def forget_poses(self) -> None:
        """The world frame was re-expressed: the kept poses belong to the old one."""
        self._poses = []

    def object_frame(self, kf_map: KeyframeMap | None) -> ObjectFrame | None:
        model = self.models.get(kf_map)
        return None if model is None else model.frame

    def prompt(self, index: int, kf_map: KeyframeMap | None) -> ObjectRegion | None:
        """The region expected in frame ``index`` before it is tracked (None: none known yet)."""
        model = self.models.get(kf_map)
        predicted = self._extrapolated(index)
        if model is not None and predicted is not None and self._camera is not None:
            region = project_region(model.points, predicted, self._camera, margin=self.margin,
                                    frame_index=index)
            if region is not None:
                return region
        return None if self.last is None else self.last.held()

    def input_mask(
        self, frame: FrameInput, index: int, kf_map: KeyframeMap | None,
        segmenter: Segmenter | None,
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(mask to track frame ``index`` with, pushed without one; the segmenter's mask if it
        gave one). The prompt's mask grown by ``grown_mask``, or the segmenter's answer to the
        prompt. (None, None) before any region is known."""
        prompt = self.prompt(index, kf_map)
        if prompt is None:
            return None, None
        if segmenter is not None and frame.size == prompt.image_size:
            answer = ask_segmenter(segmenter, frame.image, prompt, index)
            if answer is not None:
                return answer, answer
        return grown_mask(prompt), None

    def observe(
        self, frame: FrameInput, index: int, kf_map: KeyframeMap | None, *,
        T_world_cam: np.ndarray | None, camera: Camera | None, segmented: np.ndarray | None,
    ) -> tuple[ObjectRegion | None, np.ndarray | None, ObjectFrame | None]:
        """Frame ``index``'s region, ``T_cam_object`` and the object frame that refers to, after
        tracking (None for each that is unknown).

        ``T_world_cam``: the frame's pose if valid (else None); ``camera``: its input intrinsics.
        The region is the mask the app gave with ``frame`` (GIVEN) or its ``segmented`` mask
        (SEGMENTED), else the projection at the pose (PREDICTED), else the last region (HELD).
        """
        model = self.models.get(kf_map)
        if camera is not None:
            self._camera = camera
        pose = None if T_world_cam is None else np.asarray(T_world_cam, dtype=np.float64)
        if pose is not None:
            self._poses = [*self._poses[-1:], (index, pose)]
        drawn = _supplied(frame, segmented)
        if drawn is None and pose is not None and model is not None and camera is not None:
            projected = projected_mask(model.points, pose, camera)
            drawn = None if projected is None else (*projected, RegionSource.PREDICTED)
        if drawn is not None:
            mask, box, source = drawn
            self.last = region_of_mask(mask, box, margin=self.margin, frame_index=index,
                                       source=source)
        elif self.last is not None:
            self.last = self.last.held()
        if pose is None or model is None:
            return self.last, None, None
        return self.last, np.linalg.inv(pose) @ model.frame.T_world_object, model.frame

    def _extrapolated(self, index: int) -> np.ndarray | None:
        """The pose at ``index`` at constant velocity from the valid poses at ``index - 1`` and
        ``index - 2`` (the last pose alone if only it is valid; None if neither is recent)."""
        recent = [(i, pose) for i, pose in self._poses if i >= index - 2]
        if not recent or recent[-1][0] != index - 1:
            return None
        last = recent[-1][1]
        if len(recent) < 2:
            return last
        step = np.linalg.inv(recent[0][1]) @ last  # motion over one frame, in the camera frame
        return last @ step


def _supplied(
    frame: FrameInput, segmented: np.ndarray | None
) -> tuple[np.ndarray, ImageBox | None, RegionSource] | None:
    """(mask, box, source) of the region the app (its mask, else its box) or its segmenter
    supplied for ``frame``; None if neither did. A frame the app gave a region with was never
    segmented."""
    if segmented is not None:
        return segmented, None, RegionSource.SEGMENTED
    if frame.mask is not None:
        return frame.mask, None, RegionSource.GIVEN
    if frame.box is not None:
        return box_mask(frame.box, frame.size), frame.box, RegionSource.GIVEN
    return None

"""One tracking run, the same for every entry point: a tracker over a backend with the input's
camera, and the input's selected frames pushed through it.

``kvtracker track`` and ``demo``, ``eval-many`` on every engine, the examples and an app's own
loop call these two functions; nothing else assembles a tracker for a run. The documented loop
(``docs/backends.md``)::

    backend = open_backend("torch", "pi3.safetensors", threads=1)
    run_input = open_input("data/tum_fr2_desk")            # its camera: TUM's published one
    with open_tracker(TrackerConfig(), backend, run_input) as tracker:
        record = track(tracker, run_input)
    write_tum("trajectory.txt", record.trajectory())
    backend.close()
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Mapping
from typing import TYPE_CHECKING, Any

from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.runs.frames import FrameSelection, MaskFolder, read_frames
from kvtracker_sdk.runs.inputs import TrackingInput
from kvtracker_sdk.runs.run_loop import (
    BadFramePolicy,
    FrameHook,
    InputFrame,
    ProgressDisplay,
    RunRecord,
    run_frames,
)

if TYPE_CHECKING:
    from kvtracker_sdk.backends.base import Backend
    from kvtracker_sdk.tracking.core.events import StateChangeEvent
    from kvtracker_sdk.tracking.facade.tracker import Tracker
    from kvtracker_sdk.tracking.object.segmenter import Segmenter

__all__ = ["open_tracker", "track"]

ConfigLike = TrackerConfig | Mapping[str, Any] | None


def open_tracker(
    config: ConfigLike,
    backend: Backend,
    run_input: TrackingInput | None = None,
    *,
    camera: Camera | None = None,
    load_map: str | os.PathLike[str] | None = None,
    rebuild: bool = False,
    segmenter: Segmenter | None = None,
) -> Tracker:
    """A tracker over ``backend`` (which it does not close) with the camera of ``run_input``
    (``camera`` overrides it). With ``load_map`` it relocalises against that saved map;
    ``config`` then changes the map's saved configuration (None keeps it). ``segmenter``:
    object mode's optional ``Segmenter``."""
    from kvtracker_sdk.tracking.facade.tracker import Tracker

    intrinsics = camera if camera is not None else (
        run_input.camera if run_input is not None else None)
    if load_map is None:
        return Tracker(config, backend, camera=intrinsics, segmenter=segmenter)
    tracker = Tracker.from_map(load_map, backend, config, rebuild=rebuild, camera=intrinsics)
    if segmenter is not None:
        tracker.object.set_segmenter(segmenter)
    return tracker


def track(
    tracker: Tracker,
    frames: TrackingInput | Iterable[InputFrame],
    *,
    selection: FrameSelection | None = None,
    masks: MaskFolder | None = None,
    bbox: tuple[float, float, float, float] | None = None,
    bbox_first_only: bool = False,
    on_bad_frame: BadFramePolicy = BadFramePolicy.STOP,
    progress: ProgressDisplay | None = None,
    before_frame: Callable[[int, InputFrame], None] | None = None,
    after_frame: FrameHook | None = None,
    on_state_change: Callable[[StateChangeEvent], Any] | None = None,
) -> RunRecord:
    """Push the selected frames of ``frames`` (an opened input, or ready ``InputFrame``s) through
    ``tracker``; the record holds every result, event and timing, and its ``trajectory()``.

    Ends after the last frame with the pending rebuilds installed; a bad frame stops the run or
    is skipped (``on_bad_frame``), and what ended a run early is in ``record.failure`` (the
    caller decides whether to raise it). Object mode: ``masks`` (one per source frame) or
    ``bbox`` (every frame, or the first only)."""
    if isinstance(frames, TrackingInput):
        chosen = selection or FrameSelection()
        inputs: Iterable[InputFrame] = read_frames(
            frames.source, chosen, masks=masks, bbox=bbox, bbox_first_only=bbox_first_only)
    else:
        inputs = frames
    return run_frames(tracker, inputs, progress, before_frame=before_frame,
                      after_frame=after_frame, on_state_change=on_state_change,
                      on_bad_frame=on_bad_frame)

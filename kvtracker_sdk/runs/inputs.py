"""A source and the camera that took it: what every entry point opens before it tracks.

``open_input`` takes what a user names — a path (video, image folder, TUM folder, 7-Scenes
folder), a camera index or stream URL, an ``ImageSource``, or any iterable of images /
``(image, timestamp)`` pairs — and returns a :class:`TrackingInput`: the source, the camera
(given, or the one the dataset publishes: TUM, 7-Scenes) and the ground truth it ships.
``runs.session.open_tracker`` gives that camera to the ``Tracker``, so distorted frames (TUM's)
are undistorted whichever command runs them.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from kvtracker_sdk.errors import InputError
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.io.files.trajectory import Trajectory, read_trajectory
from kvtracker_sdk.io.sources.camera_files import read_camera_file
from kvtracker_sdk.io.sources.live_sources import (
    CaptureSource,
    IterableSource,
    PacedSource,
    is_live_spec,
)
from kvtracker_sdk.io.sources.sources import ImageSource, open_source

__all__ = ["InputSpec", "TrackingInput", "open_input"]

# a path, a camera index or URL, a source, or an iterable of frames
InputSpec = str | os.PathLike[str] | int | ImageSource | Iterable[Any]


@dataclass(frozen=True)
class TrackingInput:
    """The frames to track and what is known about them."""

    source: ImageSource
    camera: Camera | None  # of the source's images (distortion included); None: unknown
    ground_truth: Trajectory | None  # T_world_cam per stamp, when the source ships one
    live: bool  # a camera or a stream: frames arrive in real time, mapping should not block

    @property
    def label(self) -> str:
        """What the input was, for run records."""
        return repr(self.source)


def open_input(
    spec: InputSpec,
    *,
    camera: Camera | str | os.PathLike[str] | None = None,
    ground_truth: str | os.PathLike[str] | Trajectory | None = None,
    fps: float = 30.0,
    realtime: bool = False,
) -> TrackingInput:
    """Open ``spec`` with its camera.

    ``camera``: a ``Camera`` or an intrinsics file (JSON/YAML, ROS CameraInfo); None: the
    dataset's published intrinsics, if any. ``ground_truth``: a trajectory or a TUM/KITTI file;
    None: the source's own. ``fps`` stamps an image folder; ``realtime`` replays a file at its
    own frame rate, like a live camera.
    """
    source = _source(spec, fps)
    live = isinstance(source, CaptureSource)
    if realtime:
        source = PacedSource(source)
    if camera is None:
        known = source.camera()
    elif isinstance(camera, Camera):
        known = camera
    elif isinstance(camera, str | os.PathLike):
        known = read_camera_file(camera)
    else:
        raise InputError(f"camera must be a kvtracker_sdk.Camera or a file, got {camera!r}")
    if ground_truth is None:
        truth = source.ground_truth()
    elif isinstance(ground_truth, Trajectory):
        truth = ground_truth
    else:
        truth = read_trajectory(ground_truth)
    return TrackingInput(source, known, truth, live)


def _source(spec: InputSpec, fps: float) -> ImageSource:
    if isinstance(spec, ImageSource):
        return spec
    if isinstance(spec, int) or (
        isinstance(spec, str | os.PathLike) and is_live_spec(spec) and not Path(spec).exists()
    ):
        return open_source(str(spec), fps=fps)  # a camera index or a stream URL
    if isinstance(spec, str | os.PathLike):
        return open_source(spec, fps=fps)
    if isinstance(spec, Iterable):
        return IterableSource(spec)
    raise InputError(f"cannot track {type(spec).__name__}: give a path, a camera index, a URL, "
                     "an ImageSource or an iterable of images")

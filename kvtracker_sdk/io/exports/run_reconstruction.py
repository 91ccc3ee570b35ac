"""A :class:`Reconstruction` from what a run left on disk: a ``.kvmap`` file or a run folder.

- ``MAP.kvmap``: the keyframes (images at model resolution) and their points.
- ``RUN/`` (a ``kvtracker track`` / ``demo`` output folder holding a map saved with
  ``--save-map RUN/NAME.kvmap``): the same, and with ``all_frames`` also a camera for every
  frame of ``RUN/trajectory.txt`` (valid poses), its image re-read from the run's input
  (``run.json``) at the input's resolution. Only for scene-mode ``track`` runs: there the model
  saw the whole frame resized, so the frame's intrinsics are the map's resized back. An object
  mode crop or a simulated demo has no such frames to re-read.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from kvtracker_sdk.errors import InputError
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.io.exports.reconstruction import (
    PosedImage,
    Reconstruction,
    reconstruction_from_map,
    rigid,
)
from kvtracker_sdk.io.files.trajectory import read_tum
from kvtracker_sdk.log import get_logger

__all__ = ["find_map", "load_reconstruction"]

_log = get_logger(__name__)
_STAMP_TOLERANCE = 1e-6  # seconds: trajectory.txt stores stamps in full precision


def find_map(run_or_map: str | os.PathLike[str]) -> Path:
    """The map file of ``run_or_map``: the path itself, or the one ``.kvmap`` in a run folder."""
    path = Path(run_or_map)
    if path.is_file():
        return path
    if not path.is_dir():
        raise InputError(f"{path} is neither a map file nor a run folder")
    maps = sorted(path.glob("*.kvmap"))
    if len(maps) != 1:
        found = ", ".join(p.name for p in maps) or "none"
        raise InputError(f"{path}: a run folder must hold exactly one .kvmap (found {found}); "
                         f"save one with `kvtracker track ... --save-map {path}/map.kvmap`")
    return maps[0]


def load_reconstruction(
    run_or_map: str | os.PathLike[str],
    *,
    all_frames: bool = False,
    intrinsics: Camera | None = None,
    min_confidence: float = 0.5,
    stride: int = 1,
    force_fitted_focal: bool = False,
) -> Reconstruction:
    """Keyframe cameras and points of the map (and, with ``all_frames``, every tracked frame).

    ``intrinsics``: a calibration of the input images or the map's (any size: undistorted and
    resized to the map's images); None: the camera stored in the map, else a fit to the points
    (``io.export_camera``: an implausible fit raises IntrinsicsError unless forced).
    """
    from kvtracker_sdk.io.exports.export_camera import export_camera
    from kvtracker_sdk.io.map_file.map_file import load_map  # loads torch (the map's cache)

    map_path = find_map(run_or_map)
    loaded = load_map(map_path)
    keyframe_map = loaded.keyframe_map
    camera, origin = export_camera(keyframe_map, loaded.info, given=intrinsics,
                                   min_confidence=min_confidence,
                                   force_fitted_focal=force_fitted_focal)
    _log.info("export camera", origin=origin.value, fx=camera.fx, fy=camera.fy,
              cx=camera.cx, cy=camera.cy, width=camera.width, height=camera.height)
    reconstruction = reconstruction_from_map(keyframe_map, camera,
                                             min_confidence=min_confidence, stride=stride)
    if not all_frames:
        return reconstruction
    run = Path(run_or_map)
    if not run.is_dir():
        raise InputError("all frames need the run folder (its trajectory.txt and run.json), "
                         "not only the map")
    camera = reconstruction.images[0].intrinsics
    return reconstruction.with_images(_tracked_frames(run, camera, keyframe_map.metadata))


def _tracked_frames(run: Path, camera: Camera, metadata: Any) -> list[PosedImage]:
    from kvtracker_sdk.io.sources.sources import open_source

    document = _run_document(run)
    if document.get("command") != "track" or document.get("simulated"):
        raise InputError(f"{run}: all frames need a `kvtracker track` run (its input frames are "
                         f"re-read); this run is {document.get('command')!r}")
    mode = (document.get("config") or {}).get("mode", "scene")
    if mode != "scene":
        raise InputError(f"{run}: all frames are exported for scene-mode runs only (the object "
                         f"mode crops frames; keyframes only)")
    trajectory = read_tum(run / "trajectory.txt")
    source = open_source(document["input"])
    frames: list[PosedImage] = []
    for frame in source:
        index = np.searchsorted(trajectory.stamps, frame.timestamp)
        for candidate in (index - 1, index):
            if 0 <= candidate < len(trajectory) and \
                    abs(trajectory.stamps[candidate] - frame.timestamp) <= _STAMP_TOLERANCE:
                height, width = frame.image.shape[:2]
                frames.append(PosedImage(
                    f"frame_{len(frames):06d}.png", rigid(trajectory.poses[candidate]),
                    frame.image, camera.resized(width, height), float(frame.timestamp)))
                break
    if len(frames) != len(trajectory):
        raise InputError(f"{run}: found {len(frames)} of the {len(trajectory)} tracked frames in "
                         f"{document['input']} (was the input changed or moved?)")
    return frames


def _run_document(run: Path) -> dict[str, Any]:
    try:
        return dict(json.loads((run / "run.json").read_text(encoding="utf-8")))
    except (OSError, ValueError) as exc:
        raise InputError(f"{run}: cannot read run.json ({exc})") from exc

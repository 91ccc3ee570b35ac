"""One way from a source to a result, for every entry point (layer 7.5: above ``tracking``,
``eval``, ``viz``; below ``scale`` and ``cli``).

- ``open_backend(kind, weights, ...)`` / ``BackendSpec``: a backend by runtime name
  (torch | onnx | openvino), dtype, device, threads and runtime options;
- ``open_input(spec, camera=...)``: a source with its camera and ground truth (files, TUM,
  7-Scenes, video, camera index, URL, iterable);
- ``open_tracker(config, backend, run_input)`` and ``track(tracker, run_input)``: the tracker with
  the input's camera, and the run loop that pushes the selected frames and records everything.

``kvtracker track`` / ``demo``, ``eval-many`` (serial, local, Ray), the tracker service and the
examples call these, so that the same config and backend give the same trajectory everywhere.
"""

from kvtracker_sdk.runs.backends import BackendKind, BackendSpec, ComputeDtype, open_backend
from kvtracker_sdk.runs.frames import FrameSelection, MaskFolder
from kvtracker_sdk.runs.inputs import TrackingInput, open_input
from kvtracker_sdk.runs.run_loop import BadFramePolicy, InputFrame, RunRecord
from kvtracker_sdk.runs.session import open_tracker, track

__all__ = [
    "BackendKind",
    "BackendSpec",
    "BadFramePolicy",
    "ComputeDtype",
    "FrameSelection",
    "InputFrame",
    "MaskFolder",
    "RunRecord",
    "TrackingInput",
    "open_backend",
    "open_input",
    "open_tracker",
    "track",
]

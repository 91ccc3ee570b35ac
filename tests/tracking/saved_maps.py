"""Saved tracker sessions for the persistence tests, and reloading one in a new process.

Two sessions: one over ``SimulatedBackend`` with ``pass_jitter=0`` (a keyframe image then tracks
exactly to its saved pose), one over the golden small Pi3 model (``TorchBackend``, fp32) on real
TUM frames. Each records what a reloaded map must reproduce: the map itself and the world pose
of each keyframe image tracked against it before saving.
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from kvtracker_sdk.backends.base import Backend
from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.io.map_file.map_file import MapInfo
from kvtracker_sdk.tracking.facade.tracker import Tracker
from tests.helpers import PROJECT_ROOT, shared_path
from tests.tracking.sim_session import drive, make_tracker

SIM: dict[str, Any] = {
    "orbit": {"num_frames": 600, "turns": 0.5},
    "options": {"seed": 4, "pass_jitter": 0.0},
}


def sim_backend(**options: Any) -> SimulatedBackend:
    """The simulated backend of the saved session (``options`` change its parameters)."""
    return SimulatedBackend(orbit(**SIM["orbit"]), **{**SIM["options"], **options})


@dataclass(frozen=True)
class Saved:
    """A saved session: the file, how a child rebuilds its backend, and what the map held."""

    path: Path
    spec: dict[str, Any]
    info: MapInfo
    config: TrackerConfig
    keyframe_map: KeyframeMap
    tracked: list[np.ndarray]  # world pose of each keyframe image tracked against the saved map


def tracked_keyframes(backend: Backend, kf_map: KeyframeMap) -> list[np.ndarray]:
    """What ``push_frame`` computes for each keyframe image: track, then the map's gauge."""
    return [
        kf_map.gauge.apply_to_pose(backend.track(kf.image, kf_map.cache).pose)
        for kf in kf_map.keyframes
    ]


def save_simulated_session(folder: Path) -> Saved:
    """Keyframes at frames 0, 20, 40, 60 (ids 0-3); recover_after=5 > 4 keyframes, so a child
    tracks every keyframe image while still relocalising (no keyframe is added meanwhile)."""
    backend = sim_backend()
    config = {"keyframing": {"interval_frames": 20}, "relocalization": {"recover_after": 5}}
    path = folder / "scene.kvmap"
    with make_tracker(backend, **config) as tracker:
        drive(tracker, backend, stop=61)
        info = tracker.save_map(path)
        kf_map, saved_config = tracker.keyframe_map, tracker.config
    assert kf_map is not None and kf_map.keyframe_ids == (0, 1, 2, 3)
    spec = {"kind": "simulated", **SIM}
    return Saved(path, spec, info, saved_config, kf_map, tracked_keyframes(backend, kf_map))


def save_pi3_session(folder: Path) -> Saved:
    """7 real TUM frames, keyframes at frames 0, 3, 6 (ids 0-2), the golden small Pi3 in fp32."""
    from kvtracker_sdk.backends.torch_backend import TorchBackend

    weights = shared_path("golden", "pi3", "weights.safetensors")
    files = sorted(shared_path("data", "tum_fr2_desk", "rgb").glob("*.png"))[:7]
    backend = TorchBackend.from_pretrained(weights)
    config = TrackerConfig.from_dict(
        {"resolution": 224, "keyframing": {"interval_frames": 3},
         "relocalization": {"recover_after": 5}}
    )  # fmt: skip
    path = folder / "desk.kvmap"
    with Tracker(config, backend) as tracker:
        for file in files:
            image = cv2.cvtColor(cv2.imread(str(file)), cv2.COLOR_BGR2RGB)
            tracker.push_frame(image, timestamp=float(file.stem))
        info = tracker.save_map(path)
        kf_map = tracker.keyframe_map
    assert kf_map is not None and kf_map.keyframe_ids == (0, 1, 2)
    tracked = tracked_keyframes(backend, kf_map)
    backend.close()
    spec = {"kind": "pi3", "weights": str(weights)}
    return Saved(path, spec, info, config, kf_map, tracked)


_CHILD = """
import json, sys
from kvtracker_sdk.tracking.facade.tracker import Tracker
from tests.io.map_factory import map_digest
reports = []
for path, spec in json.loads(sys.argv[1]):
    if spec["kind"] == "pi3":
        import torch
        torch.set_num_threads(1)
        from kvtracker_sdk.backends.torch_backend import TorchBackend
        backend = TorchBackend.from_pretrained(spec["weights"])
    else:
        from kvtracker_sdk.backends.simulated import SimulatedBackend
        from kvtracker_sdk.backends.simulated_scene import orbit
        backend = SimulatedBackend(orbit(**spec["orbit"]), **spec["options"])
    with Tracker.from_map(path, backend) as tracker:
        report = {"digest": map_digest(tracker.keyframe_map), "config": tracker.config.to_dict(),
                  "status": [tracker.state.value, tracker.reason.value], "poses": [], "states": []}
        for keyframe in tracker.keyframe_map.keyframes:
            result = tracker.push_frame(keyframe.image)
            report["poses"].append(result.pose.T_world_cam.tolist())
            report["states"].append(result.state.value)
    reports.append(report)
print(json.dumps(reports))
"""


def reload_in_new_process(*saved: Saved) -> list[dict[str, Any]]:
    """One fresh interpreter (starting one with torch costs ~2 s of CPU) reloads each saved
    session in turn: it builds the backend, calls ``Tracker.from_map`` and pushes every keyframe
    image. Returns one report per session: the loaded map's digest (``map_digest``), config,
    state and reason after loading, and the pose (floats exact through JSON) and state of each
    pushed image."""
    sessions = [[str(s.path), s.spec] for s in saved]
    child = subprocess.run(
        [sys.executable, "-c", _CHILD, json.dumps(sessions)],
        cwd=PROJECT_ROOT, capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert child.returncode == 0, child.stderr
    reports: list[dict[str, Any]] = json.loads(child.stdout)
    assert len(reports) == len(saved)
    return reports

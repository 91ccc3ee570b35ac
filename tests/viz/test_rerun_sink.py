"""``RerunSink``: a file-only recording that reads back, never a global one, never half-written."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import FOCAL_PER_WIDTH, orbit, pixel_rays
from kvtracker_sdk.cache.keyframe_map import Keyframe
from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.errors import MissingDependencyError
from kvtracker_sdk.tracking.facade.tracker import Tracker
from kvtracker_sdk.viz import rerun_sink
from kvtracker_sdk.viz.rerun_sink import RerunSink

rr = pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402

SIZE = (196, 252)


def _record(path: Path, frames: int, budget: int = 32) -> None:
    """Track ``frames`` simulated frames (a keyframe every 5) into a recording at ``path``."""
    backend = SimulatedBackend(orbit(frames))
    config = TrackerConfig(resolution=224, keyframing={"interval_frames": 5,
                                                      "budget": {"max_keyframes": budget}})
    with Tracker(config, backend) as tracker, RerunSink(path) as sink:
        sink.attach(tracker)
        for frame in backend.frames(SIZE, textured=False):
            sink.set_time(frame.index, frame.timestamp)
            sink.log_frame(frame.image, tracker.push_frame(frame.image, frame.timestamp))


def test_recording_reads_back_with_every_entity(tmp_path: Path) -> None:
    path = tmp_path / "run.rrd"
    _record(path, 12)
    chunks = list(RrdReader(path).stream())
    entities = {c.entity_path for c in chunks}
    assert {"/world", "/world/camera", "/world/camera/image", "/world/points",
            "/world/trajectory", "/tracking/state", "/tracking/confidence"} <= entities
    keyframes = {e for e in entities if e.startswith("/world/keyframes/kf_") and e.count("/") == 3}
    assert keyframes == {"/world/keyframes/kf_0000", "/world/keyframes/kf_0001",
                         "/world/keyframes/kf_0002"}  # frames 0, 5, 10
    assert rr.get_global_data_recording() is None  # nothing leaked into rerun's global state
    assert [p.name for p in tmp_path.iterdir()] == ["run.rrd"]


def test_evicted_keyframes_are_cleared(tmp_path: Path) -> None:
    path = tmp_path / "run.rrd"
    _record(path, 21, budget=2)  # keyframes at 0, 5, 10, 15, 20; only two kept
    cleared = {
        c.entity_path
        for c in RrdReader(path).stream()
        if any("Clear" in name for name in c.to_record_batch().schema.names)
    }
    assert "/world/keyframes/kf_0001" in cleared and "/world/keyframes/kf_0000" not in cleared


def test_a_failed_run_leaves_no_file(tmp_path: Path) -> None:
    path = tmp_path / "run.rrd"
    with pytest.raises(RuntimeError, match="boom"), RerunSink(path) as sink:
        sink.set_time(0, 0.0)
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []  # neither the recording nor its temporary file


def test_focal_length_is_recovered_from_local_points() -> None:
    height, width = 60, 80
    rays = pixel_rays((height, width))
    depth = np.random.default_rng(0).uniform(1.0, 3.0, size=(height, width))
    keyframe = Keyframe(
        0, 0, None, np.zeros((height, width, 3), np.uint8), None, np.eye(4),
        np.full((height, width), 0.9, np.float32), (rays * depth[..., None]).astype(np.float32),
        0.9,
    )
    assert rerun_sink._focal_per_width(keyframe) == pytest.approx(FOCAL_PER_WIDTH, rel=1e-4)


def test_missing_rerun_names_the_extra(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setitem(sys.modules, "rerun", None)  # `import rerun` now raises ImportError
    with pytest.raises(MissingDependencyError, match=r"pip install -e \"\.\[viz\]\""):
        RerunSink(tmp_path / "run.rrd")
    assert list(tmp_path.iterdir()) == []

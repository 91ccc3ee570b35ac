"""``TrackerHost``: many sessions on one host equal separate trackers; sessions move between hosts
through their map files; the 4-stream Ray example equals single-process runs."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from kvtracker_sdk.errors import ConfigError, InputError, StateError
from kvtracker_sdk.scale.service import TrackerHost
from tests.examples.test_examples import load

CONFIG = {"resolution": 224, "keyframing": {"interval_frames": 20}}


@pytest.fixture(scope="module")
def example() -> Any:
    return load("ray_streams")


def test_sessions_of_one_host_equal_separate_trackers(example: Any) -> None:
    specs = example.stream_specs(2, 40)
    feeds = [example.encoded_frames(spec) for spec in specs]
    shared = TrackerHost()
    for k, spec in enumerate(specs):
        shared.open_session(f"s{k}", config=CONFIG, simulated=spec)
    interleaved: dict[int, list[dict[str, Any]]] = {0: [], 1: []}
    for i in range(40):
        for k in (0, 1):
            interleaved[k].append(shared.push(f"s{k}", *feeds[k][i]))
    assert shared.sessions() == ["s0", "s1"]
    shared.close()
    for k, spec in enumerate(specs):
        alone = TrackerHost()
        alone.open_session("x", config=CONFIG, simulated=spec)
        assert [alone.push("x", *frame) for frame in feeds[k][:40]] == interleaved[k]
        alone.close()
    assert sum(r["keyframe_id"] is not None for r in interleaved[0]) == 2  # frames 0 and 20
    assert all(np.allclose(r["T_world_cam"], r["T_world_cam"]) for r in interleaved[1])


def test_a_session_saved_on_one_host_resumes_on_another(example: Any, tmp_path: Path) -> None:
    spec = example.stream_specs(1, 60)[0]
    feed = example.encoded_frames(spec)
    first = TrackerHost()
    first.open_session("cam", config=CONFIG, simulated=spec)
    for frame in feed[:30]:
        first.push("cam", *frame)
    saved = first.save_session("cam", str(tmp_path / "cam.kvmap"))
    assert saved["keyframe_ids"] == [0, 1]
    second = TrackerHost()
    opened = second.open_session("cam", map_path=saved["path"], simulated=spec)
    assert opened["state"] == "RELOCALIZING"
    resumed = [second.push("cam", *frame) for frame in feed[30:]]
    assert resumed[-1]["state"] == "TRACKING" and resumed[-1]["pose_valid"]
    first.close()
    second.close()


def test_bad_frames_and_unknown_sessions_are_typed_errors(example: Any) -> None:
    host = TrackerHost()
    spec = example.stream_specs(1, 10)[0]
    host.open_session("cam", config=CONFIG, simulated=spec)
    with pytest.raises(StateError, match="already open"):
        host.open_session("cam", simulated=spec)
    with pytest.raises(InputError, match="not a decodable image"):
        host.push("cam", b"\x89PNG not really", 0.0)
    with pytest.raises(InputError):
        host.push("cam", b"", 0.0)
    with pytest.raises(ConfigError, match="no session"):
        host.push("other", cv2.imencode(".png", np.zeros((8, 8, 3), np.uint8))[1].tobytes(), 0.0)
    host.close_session("cam")
    with pytest.raises(ConfigError, match="no session"):
        host.close_session("cam")


def test_four_streams_on_ray_equal_single_process_runs(example: Any, ray_session: Any) -> None:
    report = example.main(["--streams", "4", "--frames", "40", "--check"])
    assert set(report["equal"]) == {"stream0", "stream1", "stream2", "stream3", "stream0-resumed"}
    assert all(report["equal"].values()), report["equal"]
    resumed = report["ray"]["stream0-resumed"]
    assert resumed[0]["state"] == "RELOCALIZING" and resumed[-1]["state"] == "TRACKING"


def test_an_object_session_needs_its_box_once(example: Any) -> None:
    spec = example.stream_specs(1, 12)[0]
    feed = example.encoded_frames(spec)
    height, width = cv2.imdecode(np.frombuffer(feed[0][0], np.uint8), cv2.IMREAD_COLOR).shape[:2]
    box = (0.3 * width, 0.3 * height, 0.7 * width, 0.7 * height)  # the sphere sits mid-frame
    host = TrackerHost()
    host.open_session("obj", config={**CONFIG, "mode": "object"}, simulated=spec)
    results = [host.push("obj", *feed[0], bbox=box)] + [host.push("obj", *f) for f in feed[1:]]
    host.close()
    assert results[0]["region"]["source"] == "given" and results[0]["region"]["box"] == list(box)
    assert {r["region"]["source"] for r in results[1:]} == {"predicted"}
    assert all(r["pose_valid"] and len(r["T_cam_object"]) == 4 for r in results)

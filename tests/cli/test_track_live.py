"""``kvtracker track`` on a (mocked) camera index and on a paced video: the same outputs as for
the files, and a Ctrl-C that ends the run cleanly with the outputs so far."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from kvtracker_sdk.io.files.trajectory import read_tum
from kvtracker_sdk.io.sources import live_sources
from kvtracker_sdk.io.sources.camera_files import DATASET_CAMERAS
from tests.cli.invoke import invoke
from tests.helpers import shared_path
from tests.io.fake_capture import FakeCapture

FAST = ("--resolution", "224", "--threads", "1", "--max-frames", "4", "--keyframe-interval", "2")


@pytest.fixture(scope="module")
def tum_bgr() -> list[np.ndarray]:
    files = sorted(shared_path("data", "tum_fr2_desk", "rgb").glob("*.png"))[:4]
    return [cv2.imread(str(f)) for f in files]


def _poses(out: Path) -> np.ndarray:
    return read_tum(out / "trajectory.txt").poses


def test_a_camera_index_gives_the_same_poses_as_the_files(
    tmp_path: Path, golden_weights: Path, tum_bgr: list[np.ndarray],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    files = invoke("track", shared_path("data", "tum_fr2_desk"), "--weights", golden_weights,
                   "--out", tmp_path / "files", *FAST)
    assert files.exit_code == 0, files.output
    capture = FakeCapture(tum_bgr)
    monkeypatch.setattr(live_sources, "_video_capture", lambda target: capture)
    camera = tmp_path / "fr2.json"  # the dataset's camera, which the TUM source applied itself
    camera.write_text(json.dumps(DATASET_CAMERAS["tum_fr2"].to_dict()))
    live = invoke("track", "0", "--weights", golden_weights, "--out", tmp_path / "live",
                  "--camera", camera, "--sync-mapping", *FAST)
    assert live.exit_code == 0, live.output
    assert capture.released
    np.testing.assert_allclose(_poses(tmp_path / "live"), _poses(tmp_path / "files"), atol=1e-9)
    run = json.loads((tmp_path / "live" / "run.json").read_text())
    assert run["command"] == "track" and run["details"]["camera"]["fx"] == 520.9


def test_ctrl_c_on_a_live_camera_ends_cleanly(
    tmp_path: Path, golden_weights: Path, tum_bgr: list[np.ndarray],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    capture = FakeCapture(tum_bgr, interrupt_at=3)  # Ctrl-C while waiting for the 4th frame
    monkeypatch.setattr(live_sources, "_video_capture", lambda target: capture)
    result = invoke("track", "0", "--weights", golden_weights, "--out", tmp_path, *FAST)
    assert result.exit_code == 130, result.output
    assert capture.released  # the camera is let go
    run = json.loads((tmp_path / "run.json").read_text())  # outputs of the frames seen
    assert run["interrupted"] and run["frames"] == 3
    assert run["config"]["threading"]["async_mapping"]  # the default for a live source
    assert (tmp_path / "trajectory.txt").is_file()


def test_a_paced_video_gives_the_same_outputs_as_the_file(
    tmp_path: Path, golden_weights: Path, tum_bgr: list[np.ndarray]
) -> None:
    video = tmp_path / "desk.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (640, 480))
    for frame in tum_bgr:
        writer.write(frame)
    writer.release()
    plain = invoke("track", video, "--weights", golden_weights, "--out", tmp_path / "a", *FAST)
    paced = invoke("track", video, "--weights", golden_weights, "--out", tmp_path / "b",
                   "--realtime", *FAST)
    assert plain.exit_code == 0 and paced.exit_code == 0, paced.output
    assert (tmp_path / "a" / "trajectory.txt").read_text() == (
        tmp_path / "b" / "trajectory.txt"
    ).read_text()

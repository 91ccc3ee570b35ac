"""Live sources: a (mocked) camera or stream, any iterable, and a paced replay of a video file."""

from __future__ import annotations

import itertools
from pathlib import Path

import cv2
import numpy as np
import pytest

from kvtracker_sdk.errors import ImageShapeError, SourceOpenError
from kvtracker_sdk.io.sources import live_sources
from kvtracker_sdk.io.sources.live_sources import (
    CaptureSource,
    IterableSource,
    PacedSource,
    is_live_spec,
)
from kvtracker_sdk.io.sources.sources import SourceFrame, VideoSource, open_source
from tests.io.fake_capture import FakeCapture


def _bgr_frames(count: int) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    return [rng.integers(0, 256, size=(48, 64, 3), dtype=np.uint8) for _ in range(count)]


def test_a_camera_index_is_read_with_capture_time_stamps(monkeypatch: pytest.MonkeyPatch) -> None:
    frames = _bgr_frames(3)
    capture = FakeCapture(frames)
    opened: list[object] = []
    monkeypatch.setattr(live_sources, "_video_capture", lambda t: opened.append(t) or capture)
    ticks = itertools.count(1000.0, 0.5)
    source = open_source("0")
    assert isinstance(source, CaptureSource) and len(source) == 0 and source.camera() is None
    source.clock = lambda: next(ticks)
    read = list(source)
    assert opened == [0]  # the index as an int: OpenCV opens a device, not a file named "0"
    assert [f.frame_index for f in read] == [0, 1, 2]
    assert [f.timestamp for f in read] == [1000.0, 1000.5, 1001.0]  # stamped when grab returned
    for got, bgr in zip(read, frames, strict=True):
        np.testing.assert_array_equal(got.image, bgr[..., ::-1])  # RGB
    assert capture.settings == {cv2.CAP_PROP_BUFFERSIZE: 1} and capture.released


def test_urls_and_app_captures(monkeypatch: pytest.MonkeyPatch) -> None:
    assert is_live_spec("rtsp://10.0.0.2:8554/cam") and is_live_spec("3") and is_live_spec(0)
    assert not is_live_spec("video.mp4") and not is_live_spec("frames/")
    targets: list[object] = []
    monkeypatch.setattr(live_sources, "_video_capture",
                        lambda t: targets.append(t) or FakeCapture([], opened=False))
    with pytest.raises(SourceOpenError, match="cannot open rtsp://10.0.0.2:8554/cam") as caught:
        open_source("rtsp://10.0.0.2:8554/cam")  # opened at once, not at the first frame
    assert caught.value.kind == "stream" and targets == ["rtsp://10.0.0.2:8554/cam"]
    stream = CaptureSource("rtsp://10.0.0.2:8554/cam")  # not opened until used
    assert "rtsp://10.0.0.2:8554/cam" in repr(stream)
    with pytest.raises(SourceOpenError):
        list(stream)
    own = FakeCapture(_bgr_frames(2))  # a capture the app opened: read, never released
    assert len(list(CaptureSource(own))) == 2 and not own.released


def test_any_iterable_of_frames() -> None:
    images = [frame[..., ::-1] for frame in _bgr_frames(3)]
    ticks = itertools.count(5.0)
    items = [images[0], (images[1], 42.0), SourceFrame(7, 43.0, images[2])]
    read = list(IterableSource(items, clock=lambda: next(ticks)))
    assert [f.timestamp for f in read] == [5.0, 42.0, 43.0]
    assert [f.frame_index for f in read] == [0, 1, 2] and read[1].image is images[1]
    with pytest.raises(ImageShapeError, match="frame 1"):
        list(IterableSource([images[0], np.zeros((4, 4))]))


def test_paced_replay_of_a_video_file(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    for frame in _bgr_frames(5):
        writer.write(frame)
    writer.release()
    now = [100.0]
    slept: list[float] = []

    def sleep(seconds: float) -> None:  # a fake clock: the test never sleeps
        slept.append(seconds)
        now[0] += seconds

    video = VideoSource(path)
    paced = PacedSource(video, speed=2.0, clock=lambda: now[0], sleep=sleep)
    read = list(paced)
    direct = list(video)
    assert [f.timestamp for f in read] == [f.timestamp for f in direct]  # stamps kept
    assert len(read) == 5 and len(paced) == len(video)
    np.testing.assert_allclose(slept, [0.05] * 4, atol=1e-9)  # 10 fps at 2x: every 50 ms
    now[0] += 1.0  # a slow consumer: frames already due are not waited for
    late = iter(PacedSource(video, clock=lambda: now[0], sleep=sleep))
    next(late)
    now[0] += 10.0
    slept.clear()
    assert len(list(late)) == 4 and slept == []

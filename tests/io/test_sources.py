"""Image sources: the real TUM folder, a video round trip, 7-Scenes and plain image folders."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from kvtracker_sdk.errors import ConfigError, InputError, SourceError
from kvtracker_sdk.io.sources.sources import (
    ImageFolderSource,
    SevenScenesSource,
    TumSource,
    VideoSource,
    open_source,
)
from tests.helpers import shared_path


def _write_rgb(path: Path, rgb: np.ndarray) -> None:
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def _solid(rgb: tuple[int, int, int], h: int = 48, w: int = 64) -> np.ndarray:
    return np.broadcast_to(np.array(rgb, dtype=np.uint8), (h, w, 3)).copy()


def test_tum_folder_yields_the_20_real_frames_in_rgb_order() -> None:
    folder = shared_path("data", "tum_fr2_desk")
    source = open_source(folder)
    assert isinstance(source, TumSource) and len(source) == 20
    frames = list(source)
    assert [f.frame_index for f in frames] == list(range(20))
    listed = [
        ln.split() for ln in (folder / "rgb.txt").read_text().splitlines() if not ln.startswith("#")
    ]
    assert [f.timestamp for f in frames] == [float(stamp) for stamp, _ in listed]
    for frame in frames:
        assert frame.image.shape == (480, 640, 3) and frame.image.dtype == np.uint8
    bgr = cv2.imread(str(folder / listed[0][1]))
    np.testing.assert_array_equal(frames[0].image, bgr[:, :, ::-1])  # RGB, not OpenCV's BGR
    truth = source.ground_truth()
    assert truth is not None and len(truth) == 20957


def test_video_round_trip_keeps_frames_colours_and_clock(tmp_path: Path) -> None:
    colours = [(255, 0, 0), (0, 255, 0), (0, 0, 255), (255, 255, 0), (20, 120, 220)]
    for name, codec in (("clip.avi", "MJPG"), ("clip.mp4", "mp4v")):
        path = tmp_path / name
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec), 10.0, (64, 48))
        assert writer.isOpened(), f"OpenCV cannot write {codec}"
        for colour in colours:
            writer.write(cv2.cvtColor(_solid(colour), cv2.COLOR_RGB2BGR))
        writer.release()

        source = open_source(path)
        assert isinstance(source, VideoSource) and len(source) == len(colours)
        for _ in range(2):  # re-iterable: each pass reopens the file
            frames = list(source)
            assert [f.frame_index for f in frames] == list(range(len(colours)))
            np.testing.assert_allclose(
                [f.timestamp for f in frames], np.arange(5) / 10.0, atol=1e-9
            )
            for frame, colour in zip(frames, colours, strict=True):
                assert frame.image.shape == (48, 64, 3) and frame.image.dtype == np.uint8
                # lossy codecs: the mean colour is within 12 levels of what was written
                np.testing.assert_allclose(frame.image.reshape(-1, 3).mean(0), colour, atol=12)


def test_seven_scenes_folder_frames_and_poses(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    poses = []
    for k in range(3):
        _write_rgb(tmp_path / f"frame-{k:06d}.color.png", _solid((10 * k, 50, 200)))
        (tmp_path / f"frame-{k:06d}.depth.png").write_bytes(b"not read")
        pose = np.eye(4)
        pose[:3, :3] = cv2.Rodrigues(rng.normal(size=3))[0]
        pose[:3, 3] = rng.normal(size=3)
        np.savetxt(tmp_path / f"frame-{k:06d}.pose.txt", pose, fmt="%.10e")
        poses.append(pose)
    source = open_source(tmp_path)
    assert isinstance(source, SevenScenesSource) and len(source) == 3
    frames = list(source)
    assert [f.timestamp for f in frames] == [0.0, 1 / 30, 2 / 30]
    assert frames[2].image[0, 0].tolist() == [20, 50, 200]
    truth = source.ground_truth()
    np.testing.assert_allclose(truth.poses, np.stack(poses), rtol=1e-9)
    assert truth.stamps.tolist() == [f.timestamp for f in frames]

    (tmp_path / "frame-000001.pose.txt").write_text("1 0 0\n")
    with pytest.raises(SourceError, match="frame-000001.pose.txt"):
        source.ground_truth()


def test_image_folder_natural_order_fps_and_grey_images(tmp_path: Path) -> None:
    for k in (10, 2, 1):
        _write_rgb(tmp_path / f"img{k}.png", _solid((k, k, k)))
    assert cv2.imwrite(str(tmp_path / "img11.jpg"), np.full((48, 64), 77, np.uint8))  # grey
    (tmp_path / "notes.txt").write_text("ignored")
    source = open_source(tmp_path, fps=4.0)
    assert isinstance(source, ImageFolderSource)
    assert [p.name for p in source.files] == ["img1.png", "img2.png", "img10.png", "img11.jpg"]
    frames = list(source)
    assert [f.timestamp for f in frames] == [0.0, 0.25, 0.5, 0.75]
    assert [int(f.image[0, 0, 0]) for f in frames[:3]] == [1, 2, 10]
    assert frames[3].image.shape == (48, 64, 3)
    np.testing.assert_allclose(frames[3].image, 77, atol=2)


def test_bad_paths_and_files_raise_source_errors(tmp_path: Path) -> None:
    assert issubclass(SourceError, InputError)
    with pytest.raises(SourceError, match="does not exist"):
        open_source(tmp_path / "missing")
    with pytest.raises(SourceError, match="no frames found"):
        open_source(tmp_path)
    _write_rgb(tmp_path / "one.png", _solid((1, 2, 3)))
    with pytest.raises(SourceError, match="single image"):
        open_source(tmp_path / "one.png")
    (tmp_path / "clip.mp4").write_bytes(b"definitely not a video")
    with pytest.raises(SourceError, match="cannot open"):
        VideoSource(tmp_path / "clip.mp4")
    with pytest.raises(ConfigError, match="fps"):
        ImageFolderSource(tmp_path, fps=0.0)

    (tmp_path / "broken.png").write_bytes(b"\x89PNG but truncated")
    with pytest.raises(SourceError, match="broken.png: cannot decode"):
        list(ImageFolderSource(tmp_path))


def test_tum_listing_errors_name_the_line_or_file(tmp_path: Path) -> None:
    (tmp_path / "rgb.txt").write_text("# header\n1.0 rgb/a.png\n")
    with pytest.raises(SourceError, match="missing, e.g."):
        TumSource(tmp_path)
    (tmp_path / "rgb.txt").write_text("# header\nabc rgb/a.png\n")
    with pytest.raises(SourceError, match="rgb.txt:2"):
        TumSource(tmp_path)
    (tmp_path / "rgb.txt").write_text("# only comments\n")
    with pytest.raises(SourceError, match="no images"):
        TumSource(tmp_path)


def test_importing_the_sources_does_not_load_opencv() -> None:
    code = "import sys, kvtracker_sdk.io.sources.sources; print('cv2' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"

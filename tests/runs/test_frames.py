"""What ``kvtracker track`` reads: frame selection, mask folders, boxes."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from kvtracker_sdk.errors import BBoxError, ConfigError, MaskError, SourceError, TrajectoryError
from kvtracker_sdk.io.files.trajectory import read_trajectory
from kvtracker_sdk.io.sources.sources import ImageFolderSource
from kvtracker_sdk.runs.frames import FrameSelection, MaskFolder, parse_bbox, read_frames


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    """Ten 16x20 frames whose red channel is their index; masks named 1.png ... 10.png."""
    frames, masks = tmp_path / "frames", tmp_path / "masks"
    frames.mkdir()
    masks.mkdir()
    for k in range(10):
        image = np.zeros((16, 20, 3), np.uint8)
        image[..., 2] = k  # BGR on disk: red
        cv2.imwrite(str(frames / f"f{k:02d}.png"), image)
        mask = np.zeros((16, 20), np.uint8)
        mask[: k + 1] = 255  # mask k covers k + 1 rows
        cv2.imwrite(str(masks / f"{k + 1}.png"), mask)
    return tmp_path


def test_selection_takes_start_stride_and_limit(folder: Path) -> None:
    source = ImageFolderSource(folder / "frames", fps=10.0)
    frames = list(read_frames(source, FrameSelection(start=1, stride=3, max_frames=2)))
    assert [int(f.image[0, 0, 0]) for f in frames] == [1, 4]
    assert [f.timestamp for f in frames] == [0.1, 0.4]
    assert FrameSelection(1, 3, 2).count(10) == 2 and FrameSelection(1, 3).count(10) == 3
    assert FrameSelection().count(0) is None  # a video that does not declare its length


def test_masks_follow_natural_order(folder: Path) -> None:
    masks = MaskFolder(folder / "masks")  # 1.png, 2.png, ..., 10.png (not 1, 10, 2, ...)
    source = ImageFolderSource(folder / "frames")
    frames = list(read_frames(source, FrameSelection(stride=4), masks=masks))
    assert [int(f.mask.sum(axis=1).astype(bool).sum()) for f in frames] == [1, 5, 9]
    assert all(f.mask.dtype == bool for f in frames)


def test_a_box_once_goes_with_the_first_selected_frame_only(folder: Path) -> None:
    source = ImageFolderSource(folder / "frames")
    box = (1.0, 2.0, 10.0, 12.0)
    once = list(read_frames(source, FrameSelection(start=2, stride=2), bbox=box,
                            bbox_first_only=True))
    assert [f.bbox for f in once] == [box, None, None, None]
    every = list(read_frames(source, FrameSelection(start=2, stride=2), bbox=box))
    assert [f.bbox for f in every] == [box] * 4


def test_too_few_masks_is_a_mask_error(folder: Path) -> None:
    (folder / "masks" / "10.png").unlink()
    frames = list(read_frames(ImageFolderSource(folder / "frames"), FrameSelection(),
                              masks=MaskFolder(folder / "masks")))
    # the frame without a mask is handed on with its error: --on-bad-frame decides
    assert len(frames) == 10 and all(f.error is None for f in frames[:9])
    assert isinstance(frames[9].error, MaskError) and "no mask for frame 9" in str(frames[9].error)


def test_an_undecodable_frame_does_not_end_the_sequence(folder: Path) -> None:
    (folder / "frames" / "f04.png").write_bytes(b"not a png")
    frames = list(read_frames(ImageFolderSource(folder / "frames"), FrameSelection()))
    assert [f.error is None for f in frames] == [True] * 4 + [False] + [True] * 5
    assert isinstance(frames[4].error, SourceError) and "f04.png" in str(frames[4].error)
    assert [int(f.image[0, 0, 0]) for f in frames[5:]] == [5, 6, 7, 8, 9]


def test_fifos_are_refused_not_waited_on(folder: Path) -> None:
    from kvtracker_sdk.io.files.regular_file import read_regular_text

    os.mkfifo(folder / "masks" / "11.png")  # reading it would block until someone writes
    with pytest.raises(MaskError, match="11.png is not a regular file"):
        MaskFolder(folder / "masks")
    fifo = folder / "pipe.json"
    os.mkfifo(fifo)
    with pytest.raises(TrajectoryError, match="FIFO"):
        read_trajectory(fifo)
    with pytest.raises(ConfigError, match="FIFO"):
        read_regular_text(fifo, ConfigError, what="--config")


@pytest.mark.parametrize("bad", ["1,2,3", "a,b,c,d", "", "1,2,3,4,5"])
def test_bad_boxes(bad: str) -> None:
    with pytest.raises(BBoxError):
        parse_bbox(bad)


def test_box_parsing_and_bad_options(tmp_path: Path) -> None:
    assert parse_bbox(" 10, 20,30 40 ") == (10.0, 20.0, 30.0, 40.0)
    with pytest.raises(ConfigError):
        FrameSelection(stride=0)
    with pytest.raises(MaskError):
        MaskFolder(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(MaskError, match="no images"):
        MaskFolder(tmp_path / "empty")

"""RGB-D input for the CLI: TUM depth.txt matched by time, image folders by position."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from kvtracker_sdk.errors import DepthError, SourceError
from kvtracker_sdk.io.sources.depth_frames import TUM_DEPTH_SCALE, DepthFolder
from kvtracker_sdk.io.sources.sources import TumSource
from kvtracker_sdk.runs.frames import FrameSelection, read_frames
from kvtracker_sdk.tracking.core.frame_input import check_depth


def _tum_sequence(folder: Path) -> None:
    """Three colour frames at 30 Hz, depth at 30 Hz shifted by 5 ms, one depth frame missing."""
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rgb, depth = ["# colour"], ["# depth"]
    for i in range(3):
        stamp = 100.0 + i / 30
        cv2.imwrite(str(folder / "rgb" / f"{stamp:.6f}.png"), np.full((8, 8, 3), 40 * i, np.uint8))
        rgb.append(f"{stamp:.6f} rgb/{stamp:.6f}.png")
        if i == 1:
            continue  # the sensor dropped this one
        cv2.imwrite(str(folder / "depth" / f"{stamp + 0.005:.6f}.png"),
                    np.full((8, 8), 5000 * (i + 1), np.uint16))
        depth.append(f"{stamp + 0.005:.6f} depth/{stamp + 0.005:.6f}.png")
    (folder / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth) + "\n")


def test_a_tum_sequence_gets_the_nearest_depth_within_20_ms(tmp_path: Path) -> None:
    _tum_sequence(tmp_path)
    for given in (tmp_path, tmp_path / "depth"):  # the sequence or its depth/ folder
        folder = DepthFolder(given)
        assert folder.scale == TUM_DEPTH_SCALE and len(folder) == 2
    frames = list(read_frames(TumSource(tmp_path), FrameSelection(), depth=folder))
    assert [f.depth is None for f in frames] == [False, True, False]
    metres = [check_depth(f.depth, f.depth_scale, (8, 8)) for f in frames if f.depth is not None]
    assert [float(m[0, 0]) for m in metres] == pytest.approx([1.0, 3.0])
    # a given scale wins over TUM's
    scaled = next(read_frames(TumSource(tmp_path), FrameSelection(), depth=folder,
                              depth_scale=0.001))
    assert scaled.depth_scale == 0.001


def test_a_plain_folder_is_matched_by_position_and_bad_files_are_bad_frames(
    tmp_path: Path
) -> None:
    for name, value in (("2.png", 2), ("10.png", 10)):
        cv2.imwrite(str(tmp_path / name), np.full((4, 4), value, np.uint16))
    folder = DepthFolder(tmp_path)
    assert folder.scale is None and folder.path_for(1, 0.0) == tmp_path / "10.png"
    assert int(folder.depth(0, 0.0)[0, 0]) == 2 and folder.depth(5, 0.0) is None  # type: ignore[index]
    (tmp_path / "11.png").write_bytes(b"not a png")
    with pytest.raises(DepthError):
        DepthFolder(tmp_path).depth(2, 0.0)
    with pytest.raises(SourceError):
        DepthFolder(tmp_path / "missing")

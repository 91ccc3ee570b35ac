"""Depth images beside a colour sequence (RGB-D): a TUM ``depth.txt`` listing or a folder of
16-bit images, matched to the colour frames.

* TUM RGB-D layout: ``DIR/depth.txt`` (``timestamp filename``) — give the sequence folder or its
  ``depth/`` folder. Each colour frame takes the depth image nearest in time, if within
  ``max_gap_s`` (0.02 s: TUM's own ``associate.py`` default; the Kinect's depth and colour run
  unsynchronised at 30 Hz). TUM's PNGs hold 5000 units per metre (``TUM_DEPTH_SCALE``).
* Any other folder: its images in natural order (``2.png`` before ``10.png``), matched to the
  colour frames by position.

Files are read unchanged (16-bit stays 16-bit; invalid = 0); the tracker converts them to metres
with the depth scale (``tracking/core/frame_input.py``).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from kvtracker_sdk.errors import DepthError, SourceError
from kvtracker_sdk.io.files.regular_file import read_regular_bytes
from kvtracker_sdk.io.sources.sources import IMAGE_SUFFIXES, read_tum_listing

__all__ = ["TUM_DEPTH_SCALE", "DepthFolder"]

TUM_DEPTH_SCALE = 1.0 / 5000.0  # metres per unit of TUM RGB-D's 16-bit depth PNGs


class DepthFolder:
    """The depth images of ``path`` (see the module docstring); ``depth(index, timestamp)``."""

    def __init__(self, path: str | os.PathLike[str], *, max_gap_s: float = 0.02) -> None:
        folder = Path(path)
        listing = next((p / "depth.txt" for p in (folder, folder.parent)
                        if (p / "depth.txt").is_file()), None)
        self.max_gap_s = float(max_gap_s)
        self.timestamps: np.ndarray | None = None
        if listing is not None:
            self.files, self.timestamps = _read_listing(listing)
            self.scale: float | None = TUM_DEPTH_SCALE
        elif folder.is_dir():
            files = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES]
            self.files = sorted(files, key=_natural_key)
            self.scale = None  # unknown: the user says (--depth-scale)
        else:
            raise SourceError(f"depth folder {folder} is not a folder")
        if not self.files:
            raise SourceError(f"depth folder {folder} holds no depth images")

    def __len__(self) -> int:
        return len(self.files)

    def __repr__(self) -> str:
        kind = "tum" if self.timestamps is not None else "by position"
        return f"DepthFolder({len(self.files)} images, {kind})"

    def path_for(self, index: int, timestamp: float) -> Path | None:
        """The depth image of colour frame ``index`` at ``timestamp`` (None: none near)."""
        if self.timestamps is None:
            return self.files[index] if index < len(self.files) else None
        nearest = int(np.argmin(np.abs(self.timestamps - timestamp)))
        if abs(float(self.timestamps[nearest]) - timestamp) > self.max_gap_s:
            return None
        return self.files[nearest]

    def depth(self, index: int, timestamp: float) -> np.ndarray | None:
        """The raw depth image [H, W] (16-bit or float, as stored) of a colour frame, or None."""
        import cv2  # OpenCV loads only when a depth image is read

        path = self.path_for(index, timestamp)
        if path is None:
            return None
        data = read_regular_bytes(path, DepthError, what="depth image")  # never blocks
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
        if image is None or image.ndim != 2:
            raise DepthError(f"{path}: cannot decode a one-channel depth image")
        return image


def _read_listing(listing: Path) -> tuple[list[Path], np.ndarray]:
    files, stamps, _ = read_tum_listing(listing)
    return files, stamps


def _natural_key(path: Path) -> list[int | str]:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]

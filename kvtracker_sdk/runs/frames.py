"""The frames a run tracks: a source's selected frames, with object masks or a box in object mode.

Every entry point reads its frames here (``runs.track``), so ``kvtracker track``, ``eval-many``
and an app's loop push the same frames. The source is opened by ``runs.inputs.open_input``
(video, image folder, TUM folder, 7-Scenes folder, camera, stream, iterable). Object mode needs,
per frame, a mask or a box:

- ``--masks DIR``: one mask image per frame, matched by position in natural order (``2.png``
  before ``10.png``); non-zero pixels are the object. Their count must cover the frames used.
- ``--bbox x0,y0,x1,y1``: one box in pixels of the input frames, used for every frame (an
  object that stays roughly in place, e.g. on a turntable), or with ``--bbox-once`` for the
  first frame only (the tracker predicts the object's region after it).

RGB-D: ``--depth DIR`` adds a depth image registered to each colour frame (``io/sources/depth_frames.py``:
a TUM ``depth.txt`` matched by time, or images matched by position); the map becomes metric.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from kvtracker_sdk.errors import BBoxError, ConfigError, InputError, MaskError
from kvtracker_sdk.io.files.regular_file import read_regular_bytes
from kvtracker_sdk.io.sources.depth_frames import DepthFolder
from kvtracker_sdk.io.sources.sources import IMAGE_SUFFIXES, ImageSource, SourceFrame, read_rgb
from kvtracker_sdk.runs.run_loop import InputFrame

__all__ = ["FrameSelection", "MaskFolder", "parse_bbox", "read_frames"]


@dataclass(frozen=True)
class FrameSelection:
    """Which source frames to use: every ``stride``-th from ``start``, at most ``max_frames``."""

    start: int = 0
    stride: int = 1
    max_frames: int | None = None

    def __post_init__(self) -> None:
        if self.start < 0 or self.stride < 1 or (self.max_frames is not None and self.max_frames < 1):
            raise ConfigError(
                f"frame selection needs start >= 0, stride >= 1, max frames >= 1; got "
                f"{self.start}, {self.stride}, {self.max_frames}"
            )

    def count(self, available: int) -> int | None:
        """Frames selected out of ``available`` (None when the source cannot tell: 0)."""
        if available <= 0:
            return self.max_frames
        selected = len(range(self.start, available, self.stride))
        return selected if self.max_frames is None else min(selected, self.max_frames)


class MaskFolder:
    """The mask images of a folder in natural order; ``mask(i)`` is a bool [H, W] array."""

    def __init__(self, folder: Path) -> None:
        if not folder.is_dir():
            raise MaskError(f"mask folder {folder} is not a folder")
        files = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES]
        if not files:
            raise MaskError(f"mask folder {folder} holds no images")
        for path in files:  # a FIFO named 3.png would block the run when its mask is read
            if not path.is_file():
                raise MaskError(f"mask folder {folder}: {path.name} is not a regular file")
        self.files = sorted(files, key=_natural_key)

    def __len__(self) -> int:
        return len(self.files)

    def mask(self, index: int) -> np.ndarray:
        import cv2  # OpenCV loads only when a mask is read

        if index >= len(self.files):
            raise MaskError(f"no mask for frame {index}: the mask folder has {len(self.files)}")
        data = read_regular_bytes(self.files[index], MaskError, what="mask")  # never blocks
        grey = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE) if data else None
        if grey is None:
            raise MaskError(f"{self.files[index]}: cannot decode the mask image")
        return grey > 0


def parse_bbox(text: str) -> tuple[float, float, float, float]:
    """``"x0,y0,x1,y1"`` (pixels) -> a tuple; the tracker checks it against each frame."""
    parts = [p for p in re.split(r"[,\s]+", text.strip()) if p]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError as exc:
        raise BBoxError(f"--bbox {text!r}: expected four numbers x0,y0,x1,y1") from exc
    if len(values) != 4:
        raise BBoxError(f"--bbox {text!r}: expected four numbers x0,y0,x1,y1, got {len(values)}")
    return values[0], values[1], values[2], values[3]


def read_frames(
    source: ImageSource,
    selection: FrameSelection,
    *,
    masks: MaskFolder | None = None,
    bbox: tuple[float, float, float, float] | None = None,
    bbox_first_only: bool = False,
    depth: DepthFolder | None = None,
    depth_scale: float | None = None,
) -> Iterator[InputFrame]:
    """The selected frames of ``source``, each with its mask (by source position) or the box
    (``bbox_first_only``: the first selected frame only), and its depth image from ``depth``
    (raw units, ``depth_scale`` metres each; None: the folder's own, TUM's 1/5000).

    Skipped frames are still decoded (sources read sequentially, as a video must), so a large
    ``stride`` saves tracking time, not decoding time. A frame or mask that cannot be read is
    yielded with its ``error`` set (the run loop's ``--on-bad-frame`` policy decides).
    """
    used = 0
    for frame in _source_frames(source):
        offset = frame.frame_index - selection.start
        if offset < 0 or offset % selection.stride:
            continue
        if selection.max_frames is not None and used >= selection.max_frames:
            return
        used += 1
        if isinstance(frame, _Unreadable):
            yield InputFrame(_NO_IMAGE, frame.timestamp, error=frame.error)
            continue
        try:
            mask = masks.mask(frame.frame_index) if masks is not None else None
            image_depth = (depth.depth(frame.frame_index, frame.timestamp)
                           if depth is not None else None)
        except InputError as error:  # a bad mask or depth image: the --on-bad-frame policy
            yield InputFrame(frame.image, frame.timestamp, error=error)
            continue
        box = None if bbox_first_only and used > 1 else bbox
        scale = depth_scale if depth_scale is not None or depth is None else depth.scale
        yield InputFrame(frame.image, frame.timestamp, mask=mask, bbox=box, depth=image_depth,
                         depth_scale=scale)


class _Unreadable(NamedTuple):
    """A source frame that could not be decoded."""

    frame_index: int
    timestamp: float
    error: InputError


_NO_IMAGE = np.zeros((0, 0, 3), np.uint8)


def _source_frames(source: ImageSource) -> Iterator[SourceFrame | _Unreadable]:
    """The source's frames; an undecodable one becomes an ``_Unreadable`` in its place.

    A list of image files is read file by file here, so that one bad file does not end the
    sequence (the source's own iterator stops at its first error); a stream (a video) cannot be
    resumed after an error, so that error is its last item.
    """
    files, stamps = getattr(source, "files", None), getattr(source, "timestamps", None)
    if isinstance(files, list) and stamps is not None and len(stamps) == len(files):
        for index, (stamp, file) in enumerate(zip(stamps, files, strict=True)):
            try:
                yield SourceFrame(index, float(stamp), read_rgb(file))
            except InputError as error:
                yield _Unreadable(index, float(stamp), error)
        return
    index = 0
    iterator = iter(source)
    while True:
        try:
            frame = next(iterator)
        except StopIteration:
            return
        except InputError as error:
            yield _Unreadable(index, float("nan"), error)
            return
        index = frame.frame_index + 1
        yield frame


def _natural_key(path: Path) -> list[int | str]:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]

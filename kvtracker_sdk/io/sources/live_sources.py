"""Live image sources: a camera, a network stream, any Python iterable, and a paced replay.

They yield the same :class:`~kvtracker_sdk.io.sources.sources.SourceFrame` as the file sources, so the
tracker and the CLI treat them alike; their length is unknown (``len() == 0``).

- :class:`CaptureSource`: an OpenCV ``VideoCapture`` — a camera index (``0``), a URL or RTSP
  stream (``rtsp://...``, ``http://...``), or a capture object the app opened. Each frame is
  stamped with the wall-clock time (``time.time()``, seconds since the epoch) at which
  ``grab()`` returned, i.e. its capture time as far as the host can tell; the decode
  (``retrieve()``) comes after the stamp. Cameras get a one-frame driver buffer
  (``CAP_PROP_BUFFERSIZE = 1``) so that a slow consumer reads recent frames, not a backlog.
- :class:`IterableSource`: any iterable of HxWx3 uint8 RGB images, ``(image, timestamp)`` pairs or
  ``SourceFrame``s; images without a stamp get their capture time (when the iterator produced
  them).
- :class:`PacedSource`: another source replayed at the pace of its timestamps (a video file
  played as if it were a live camera; stamps kept, so the outputs equal the file's).

:func:`open_live_source` turns a command-line INPUT (``"0"``, ``"rtsp://..."``) into a source.
"""

from __future__ import annotations

import os
import re
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from kvtracker_sdk.errors import ConfigError, ImageShapeError, SourceError, SourceOpenError
from kvtracker_sdk.io.sources.opencv_messages import opencv_messages_logged
from kvtracker_sdk.io.sources.sources import ImageSource, SourceFrame

__all__ = [
    "CaptureSource",
    "IterableSource",
    "PacedSource",
    "is_live_spec",
    "open_live_source",
]

_URL = re.compile(r"^[a-z][a-z0-9+.-]*://", re.IGNORECASE)
Clock = Callable[[], float]


def is_live_spec(spec: str | os.PathLike[str] | int) -> bool:
    """True for a camera index (``0``, ``"1"``) or a stream URL (``rtsp://...``)."""
    if isinstance(spec, int):
        return True
    text = os.fspath(spec)
    return text.isdigit() or bool(_URL.match(text))


def _video_capture(target: int | str) -> Any:
    """``cv2.VideoCapture(target)`` (a seam for tests: no device, no network)."""
    import cv2

    return cv2.VideoCapture(target)


class CaptureSource(ImageSource):
    """Frames read from an OpenCV capture (see the module docstring); iterate once per open."""

    def __init__(self, target: int | str | Any, *, clock: Clock = time.time) -> None:
        self.target = target
        self.clock = clock
        label = str(target) if isinstance(target, int | str) else type(target).__name__
        self.path = Path(label)  # ImageSource's display name; a URL is kept whole in `target`
        self.label = label
        self._opened: Any = None  # a capture opened by open(), handed to the first iteration

    def open(self) -> CaptureSource:
        """Open the camera or stream now (not at the first frame): ``SourceOpenError`` if it
        cannot be opened, so that nothing is loaded or written for a source that does not exist.
        OpenCV's own messages go to the log (``opencv_message``), not to the terminal."""
        if self._opened is None and isinstance(self.target, int | str):
            self._opened = self._open_capture()
        return self

    def _open_capture(self) -> Any:
        camera = isinstance(self.target, int)
        with opencv_messages_logged(self.label) as messages:
            capture = _video_capture(self.target)
            opened = bool(capture.isOpened())
        if not opened:
            capture.release()
            said = f" (OpenCV: {messages[0]})" if messages else ""
            what = f"camera {self.label}" if camera else self.label
            reason = ("no such camera, or it is busy or not permitted" if camera else
                      "the stream is unreachable or in a format OpenCV cannot decode")
            raise SourceOpenError(f"cannot open {what}: {reason}{said}",
                                  kind="camera" if camera else "stream", target=self.label)
        return capture

    def __len__(self) -> int:
        return 0  # unknown: a live stream ends when the device or the app stops it

    def __iter__(self) -> Iterator[SourceFrame]:
        import cv2

        opened_here = isinstance(self.target, int | str)
        capture: Any
        if opened_here:
            capture, self._opened = self._opened or self._open_capture(), None
        else:
            capture = self.target
            if not capture.isOpened():
                raise SourceOpenError(f"cannot open {self.label}: the capture is not opened",
                                      kind="stream", target=self.label)
        if isinstance(self.target, int):
            capture.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # recent frames, not a backlog
        try:
            index = 0
            while capture.grab():
                stamp = self.clock()
                ok, bgr = capture.retrieve()
                if not ok or bgr is None:
                    return
                yield SourceFrame(index, float(stamp), cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
                index += 1
        finally:
            if opened_here:
                capture.release()

    def __repr__(self) -> str:
        return f"CaptureSource({self.label!r})"


class IterableSource(ImageSource):
    """Frames from any iterable (images, ``(image, timestamp)`` pairs or ``SourceFrame``s)."""

    def __init__(self, frames: Iterable[Any], *, clock: Clock = time.time) -> None:
        self.frames = frames
        self.clock = clock
        self.path = Path(type(frames).__name__)

    def __len__(self) -> int:
        try:
            return len(self.frames)  # type: ignore[arg-type]
        except TypeError:
            return 0

    def __iter__(self) -> Iterator[SourceFrame]:
        for index, item in enumerate(self.frames):
            if isinstance(item, SourceFrame):
                image, stamp = item.image, item.timestamp
            elif isinstance(item, tuple) and len(item) == 2:
                image, stamp = item
            else:
                image, stamp = item, None
            if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3:
                raise ImageShapeError(
                    f"frame {index} of the iterable is not an HxWx3 image: "
                    f"{getattr(image, 'shape', type(image).__name__)}"
                )
            yield SourceFrame(index, float(self.clock() if stamp is None else stamp), image)


class PacedSource(ImageSource):
    """``source`` replayed in real time: frame k is released ``(t_k - t_0) / speed`` seconds
    after the first; a consumer slower than that sees the frames late, never skipped."""

    def __init__(
        self, source: ImageSource, *, speed: float = 1.0, clock: Clock = time.perf_counter,
        sleep: Callable[[float], Any] = time.sleep,
    ) -> None:
        if not (np.isfinite(speed) and speed > 0):
            raise ConfigError(f"replay speed must be > 0, got {speed}")
        self.source, self.speed, self.clock, self.sleep = source, float(speed), clock, sleep
        self.path = source.path

    def __len__(self) -> int:
        return len(self.source)

    def __iter__(self) -> Iterator[SourceFrame]:
        start_clock = first_stamp = None
        for frame in self.source:
            if start_clock is None or first_stamp is None:
                start_clock, first_stamp = self.clock(), frame.timestamp
            else:
                due = start_clock + (frame.timestamp - first_stamp) / self.speed
                wait = due - self.clock()
                if wait > 0:
                    self.sleep(wait)
            yield frame

    def ground_truth(self) -> Any:
        return self.source.ground_truth()

    def camera(self) -> Any:
        return self.source.camera()

    def __repr__(self) -> str:
        return f"PacedSource({self.source!r}, speed={self.speed})"


def open_live_source(spec: str | int) -> CaptureSource:
    """The capture source of a camera index (``0``) or a stream URL, opened: ``SourceOpenError``
    when it cannot be opened, ``SourceError`` when ``spec`` is neither."""
    if not is_live_spec(spec):
        raise SourceError(f"{spec!r} is neither a camera index nor a stream URL")
    target: int | str = int(spec) if isinstance(spec, int) or str(spec).isdigit() else str(spec)
    return CaptureSource(target).open()

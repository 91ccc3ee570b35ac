"""Image sources: iterate the frames of a folder, a video or a dataset sequence as RGB arrays.

Every source yields :class:`SourceFrame` tuples ``(index, timestamp, image)`` with ``image`` an
HxWx3 uint8 **RGB** array (OpenCV decodes to BGR; the conversion happens here, once) and
``timestamp`` in seconds. Sources read lazily, one frame at a time, and can be iterated again.

- :class:`ImageFolderSource`: the images of a folder in natural order (``2.png`` before
  ``10.png``), stamped ``index / fps``.
- :class:`VideoSource`: a video file decoded by OpenCV, stamped by the container's clock.
- :class:`TumSource`: a TUM RGB-D sequence folder (``rgb.txt``: ``timestamp filename``);
  :meth:`~ImageSource.ground_truth` reads its ``groundtruth.txt``.
- :class:`SevenScenesSource`: a 7-Scenes sequence folder (``frame-000000.color.png`` with
  ``frame-000000.pose.txt``, a 4x4 camera-to-world matrix); frames stamped ``index / 30``
  (the Kinect's rate: the dataset has no stamps); its poses are its ground truth.

:func:`open_source` picks the right one for a path (or a live camera / stream: ``live_sources``).
OpenCV is imported when a frame is read.
"""

from __future__ import annotations

import abc
import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from kvtracker_sdk.errors import (
    ConfigError,
    FrameDecodeError,
    SourceError,
    SourceOpenError,
    TrajectoryError,
)
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.io.files.trajectory import Trajectory, read_tum
from kvtracker_sdk.io.sources.camera_files import DATASET_CAMERAS
from kvtracker_sdk.io.sources.opencv_messages import opencv_messages_logged

__all__ = [
    "ImageFolderSource",
    "ImageSource",
    "SevenScenesSource",
    "SourceFrame",
    "TumSource",
    "VideoSource",
    "open_source",
    "read_rgb",
    "read_tum_listing",
]

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp"})
SEVEN_SCENES_FPS = 30.0


class SourceFrame(NamedTuple):
    """One frame: its position in the source (from 0), its time in seconds, HxWx3 uint8 RGB pixels."""

    frame_index: int
    timestamp: float
    image: np.ndarray


class ImageSource(abc.ABC):
    """A finite, re-iterable sequence of :class:`SourceFrame` read from ``path``."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)

    @abc.abstractmethod
    def __len__(self) -> int:
        """Number of frames (for a video, as the container declares it)."""

    @abc.abstractmethod
    def __iter__(self) -> Iterator[SourceFrame]:
        """Frames in order, decoded one at a time."""

    def ground_truth(self) -> Trajectory | None:
        """The sequence's ground-truth ``T_world_cam`` trajectory, if it ships one."""
        return None

    def camera(self) -> Camera | None:
        """The intrinsics the dataset publishes for these frames (None when unknown)."""
        return None

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.path)!r}, frames={len(self)})"


class _FileListSource(ImageSource):
    """A source that is a list of image files with one timestamp each."""

    def __init__(self, path: str | os.PathLike[str], files: list[Path], stamps: np.ndarray) -> None:
        super().__init__(path)
        if not files:
            raise SourceError(f"{path}: no images found")
        missing = [str(f) for f in files if not f.is_file()]
        if missing:
            raise SourceError(
                f"{path}: {len(missing)} listed images are missing, e.g. {missing[0]}"
            )
        self.files = files
        self.timestamps = np.asarray(stamps, dtype=np.float64)

    def __len__(self) -> int:
        return len(self.files)

    def __iter__(self) -> Iterator[SourceFrame]:
        for index, (stamp, file) in enumerate(zip(self.timestamps, self.files, strict=True)):
            yield SourceFrame(index, float(stamp), read_rgb(file))


class ImageFolderSource(_FileListSource):
    """The images directly inside a folder, in natural order, stamped ``index / fps``."""

    def __init__(self, path: str | os.PathLike[str], *, fps: float = 30.0) -> None:
        folder = Path(path)
        if not folder.is_dir():
            raise SourceError(f"{folder} is not a folder")
        if not (np.isfinite(fps) and fps > 0):
            raise ConfigError(f"fps must be > 0, got {fps}")
        files = sorted(_image_files(folder), key=_natural_key)
        super().__init__(folder, files, np.arange(len(files)) / fps)



def read_tum_listing(listing: Path) -> tuple[list[Path], np.ndarray, list[str]]:
    """A TUM listing (``rgb.txt``, ``depth.txt``: ``timestamp filename`` per line, ``#``
    comments): the files (beside the listing), their stamps [N] float64 (seconds), and the
    comment lines. ``SourceError`` naming the line for anything else."""
    stamps, files, comments = [], [], []
    try:
        lines = listing.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise SourceError(f"cannot read {listing} ({exc})") from exc
    for number, line in enumerate(lines, start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            comments.append(line)
            continue
        try:
            if len(fields) != 2:
                raise ValueError(f"{len(fields)} fields")
            stamps.append(float(fields[0]))
        except ValueError as exc:
            raise SourceError(f"{listing}:{number}: expected 'timestamp filename' ({exc})") from exc
        files.append(listing.parent / fields[1])
    return files, np.array(stamps, dtype=np.float64), comments


class TumSource(_FileListSource):
    """A TUM RGB-D sequence folder: the images listed in ``rgb.txt`` with their stamps."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        folder = Path(path)
        listing = folder / "rgb.txt"
        files, stamps, comments = read_tum_listing(listing)
        self._camera_name: str | None = next(
            (name for name in map(_tum_camera_name, comments) if name), None)
        super().__init__(folder, files, stamps)
        self._camera_name = _tum_camera_name(folder.resolve().name) or self._camera_name

    def camera(self) -> Camera | None:
        """TUM's published intrinsics of the sequence's camera (freiburg 1, 2 or 3, found in the
        folder name or in ``rgb.txt``'s header); fr1 and fr2 frames are distorted."""
        return None if self._camera_name is None else DATASET_CAMERAS[self._camera_name]

    def ground_truth(self) -> Trajectory | None:
        """``groundtruth.txt`` (the whole motion-capture trajectory, not matched to frames)."""
        path = self.path / "groundtruth.txt"
        return read_tum(path) if path.is_file() else None


class SevenScenesSource(_FileListSource):
    """A 7-Scenes sequence folder (``seq-XX``): colour frames and camera-to-world pose files."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        folder = Path(path)
        files = sorted(folder.glob("frame-*.color.png"))
        super().__init__(folder, files, np.arange(len(files)) / SEVEN_SCENES_FPS)

    def camera(self) -> Camera:
        """7-Scenes' published intrinsics (the Kinect's: 585 px focal, centre (320, 240))."""
        return DATASET_CAMERAS["7scenes"]

    def ground_truth(self) -> Trajectory:
        """The ``frame-XXXXXX.pose.txt`` matrices (``T_world_cam``) stamped like the frames."""
        poses = np.empty((len(self.files), 4, 4))
        for k, image in enumerate(self.files):
            pose_file = image.with_name(image.name.replace(".color.png", ".pose.txt"))
            try:
                poses[k] = np.loadtxt(pose_file, dtype=np.float64).reshape(4, 4)
            except (OSError, ValueError) as exc:
                raise SourceError(f"{pose_file}: not a readable 4x4 pose ({exc})") from exc
        try:
            return Trajectory(self.timestamps, poses)
        except TrajectoryError as exc:
            raise SourceError(f"{self.path}: bad poses ({exc})") from exc


class VideoSource(ImageSource):
    """A video file decoded with OpenCV; stamps are the container's presentation times."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        super().__init__(path)
        capture = _open_video(self.path)
        try:
            self._frame_count = max(int(capture.get(_cv2().CAP_PROP_FRAME_COUNT)), 0)
        finally:
            capture.release()

    def __len__(self) -> int:
        return self._frame_count

    def __iter__(self) -> Iterator[SourceFrame]:
        cv2 = _cv2()
        capture = _open_video(self.path)
        try:
            index = 0
            while True:
                ok, bgr = capture.read()
                if not ok:
                    return
                stamp = capture.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
                yield SourceFrame(index, stamp, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
                index += 1
        finally:
            capture.release()


def open_source(path: str | os.PathLike[str], *, fps: float = 30.0) -> ImageSource:
    """The source for ``path``: a video file, a TUM folder (``rgb.txt``), a 7-Scenes folder
    (``frame-*.color.png``), a folder of images (stamped ``index / fps``), or — when no such
    path exists — a camera index (``"0"``) or a stream URL (``rtsp://...``), read live by
    ``io.live_sources.CaptureSource``."""
    target = Path(path)
    from kvtracker_sdk.io.sources.live_sources import (  # imports this module
        is_live_spec,
        open_live_source,
    )

    if is_live_spec(path) and not target.exists():  # a camera index or a stream URL
        return open_live_source(os.fspath(path))
    if target.is_file():
        if target.suffix.lower() in IMAGE_SUFFIXES:
            raise SourceError(f"{target} is a single image; pass the folder that holds the frames")
        return VideoSource(target)
    if not target.is_dir():
        raise SourceOpenError(f"{target} does not exist", kind="path", target=str(target))
    if (target / "rgb.txt").is_file():
        return TumSource(target)
    if any(target.glob("frame-*.color.png")):
        return SevenScenesSource(target)
    if any(_image_files(target)):
        return ImageFolderSource(target, fps=fps)
    raise SourceError(
        f"{target}: no frames found (looked for rgb.txt, frame-*.color.png and image files "
        f"with suffixes {', '.join(sorted(IMAGE_SUFFIXES))})"
    )


def read_rgb(path: str | os.PathLike[str]) -> np.ndarray:
    """An image file as HxWx3 uint8 RGB (grey and alpha images converted, 16-bit scaled down)."""
    cv2 = _cv2()
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FrameDecodeError(f"{path}: cannot decode the image")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _tum_camera_name(text: str) -> str | None:
    """``tum_fr1``/``tum_fr2``/``tum_fr3`` when ``text`` names a TUM freiburg camera."""
    match = re.search(r"(?:freiburg|fr)([123])(?![0-9])", text.lower())
    return None if match is None else f"tum_fr{match.group(1)}"


def _image_files(folder: Path) -> Iterator[Path]:
    return (p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def _natural_key(path: Path) -> list[int | str]:
    """Sort key reading digit runs as numbers: ``frame2`` < ``frame10``."""
    parts: list[int | str] = []
    for text in re.split(r"(\d+)", path.name):
        parts.append(int(text) if text.isdigit() else text.lower())
    return parts


def _open_video(path: Path) -> Any:
    cv2 = _cv2()
    if not path.is_file():
        raise SourceOpenError(f"{path} does not exist", kind="path", target=str(path))
    with opencv_messages_logged(str(path)):
        capture = cv2.VideoCapture(str(path))
        opened = capture.isOpened()
    if not opened:
        capture.release()
        raise SourceOpenError(f"{path}: OpenCV cannot open this video (unknown format or codec)",
                              kind="video", target=str(path))
    return capture


def _cv2() -> Any:
    # Imported here so that `import kvtracker_sdk` stays cheap (OpenCV is slow to load).
    import cv2

    return cv2

"""The one exception tree of kvtracker-sdk.

Every error the SDK raises on purpose derives from :class:`KVTrackerError`, so an app can catch
the whole family with one ``except``. Third-party exceptions are re-raised as one of these with
``raise ... from exc`` (the habit of ``httpx/_exceptions.py``).

Losing track is *not* an exception: it is a state in the frame result. Exceptions are for misuse
and bad input, and a raised input error leaves the tracker and its map untouched.

    KVTrackerError
    ├── ConfigError                      invalid configuration values
    ├── InputError                       a frame, mask or bbox the tracker cannot use
    │   ├── ImageShapeError
    │   ├── ImageDtypeError
    │   ├── NonFiniteImageError
    │   ├── MaskError
    │   ├── BBoxError
    │   ├── ResolutionChangedError
    │   ├── DepthError                   a depth image or its depth scale cannot be used
    │   ├── GravityError                 a gravity vector is not 3 finite numbers, or is zero
    │   ├── SourceError                  an image source (folder, video, dataset) cannot be read
    │   │   ├── SourceOpenError          cannot be opened at all: no such camera, stream or path
    │   │   └── FrameDecodeError         one frame of an opened source cannot be decoded
    │   ├── TrajectoryError              a trajectory file or pose array is malformed
    │   ├── EvaluationError              trajectories cannot be compared (no matches, too short)
    │   └── IntrinsicsError              no usable camera for an export (an implausible fitted focal)
    ├── StateError                       call not allowed in the current state (closed tracker, ...)
    │   └── IllegalTransitionError       a transition missing from the state table (a bug)
    ├── ModelError
    │   ├── WeightsNotFoundError         weights not found / hub unreachable (says how to pass a file)
    │   └── CheckpointMismatchError      missing / unexpected / wrongly shaped keys (lists them)
    ├── CacheError                       KV cache misuse (layout, capacity, unknown keyframe)
    ├── OutputError                      an output file or folder cannot be written (also OSError)
    ├── BackendError
    │   ├── BackendMismatchError         fingerprints or cache layouts disagree
    │   ├── MappingFailedError           a mapping pass failed (the cause is ``__cause__``)
    │   ├── TrackingFailedError          a tracking pass failed or gave non-finite output
    │   ├── CompileError                 torch.compile is unavailable or failed (no fallback asked)
    │   └── MissingDependencyError       an optional extra is not installed (names it)
    └── MapError                         map files (``.kvmap``)
        ├── MapFormatError               not a map file / malformed header
        ├── MapVersionError              format too old or too new
        ├── MapModelMismatchError        made by another model, family or resolution
        ├── MapCorruptedError            checksum or size mismatch in the tensor data
        ├── MapPreprocessingError        extending a map made by another preprocessing (not asked)
        └── MapIOError                   the file cannot be read or written (missing, disk full)
"""

from __future__ import annotations

__all__ = [
    "BBoxError",
    "BackendError",
    "BackendMismatchError",
    "CacheError",
    "CheckpointMismatchError",
    "CompileError",
    "ConfigError",
    "DepthError",
    "EvaluationError",
    "GravityError",
    "IllegalTransitionError",
    "ImageDtypeError",
    "ImageShapeError",
    "InputError",
    "IntrinsicsError",
    "KVTrackerError",
    "MapCorruptedError",
    "MapError",
    "MapFormatError",
    "MapIOError",
    "MapModelMismatchError",
    "MapPreprocessingError",
    "MapVersionError",
    "MappingFailedError",
    "MaskError",
    "MissingDependencyError",
    "install_command",
    "ModelError",
    "NonFiniteImageError",
    "OutputError",
    "ResolutionChangedError",
    "SourceError",
    "SourceOpenError",
    "FrameDecodeError",
    "StateError",
    "TrackingFailedError",
    "TrajectoryError",
    "WeightsNotFoundError",
]


class KVTrackerError(Exception):
    """Base class of every error raised by kvtracker-sdk.

    ``hint`` (optional) says what to do about this very error where the raising code knows better
    than its class (the CLI prints it instead of the class's generic hint).
    """

    def __init__(self, *args: object, hint: str | None = None) -> None:
        super().__init__(*args)
        self.hint = hint


class ConfigError(KVTrackerError, ValueError):
    """A configuration value is invalid or inconsistent."""


class InputError(KVTrackerError, ValueError):
    """A frame, mask or box cannot be used. The tracker and its map are left untouched."""


class ImageShapeError(InputError):
    """The image is not HxWx3 (or is too small for the model)."""


class ImageDtypeError(InputError):
    """The image dtype is not uint8 or a float type in [0, 1]."""


class NonFiniteImageError(InputError):
    """The image contains NaN or infinite values."""


class MaskError(InputError):
    """The mask has the wrong shape or dtype, or selects no pixel."""


class BBoxError(InputError):
    """The bounding box is malformed or lies outside the image."""


class ResolutionChangedError(InputError):
    """The image size changed in the middle of a session."""


class DepthError(InputError):
    """The depth image has the wrong shape, dtype or values, or its depth scale is missing."""


class GravityError(InputError):
    """The gravity vector is not 3 finite numbers, or is (nearly) zero."""


class SourceError(InputError):
    """An image source cannot be opened or read (missing path, bad list file, undecodable frame)."""


class SourceOpenError(SourceError):
    """A source cannot be opened at all: ``kind`` says which (``"camera"``: no such camera index,
    or it is busy or forbidden; ``"stream"``: the URL is unreachable or OpenCV cannot decode it;
    ``"path"``: no such file or folder; ``"video"``: a file OpenCV cannot decode). ``target`` is
    what was asked for. Raised when the source
    is opened, before anything is tracked or written."""

    def __init__(
        self, message: str, *, kind: str = "path", target: str = "", hint: str | None = None
    ) -> None:
        super().__init__(message, hint=hint)
        self.kind = kind
        self.target = target


class FrameDecodeError(SourceError):
    """One frame of an opened source cannot be decoded (a damaged or non-image file)."""


class TrajectoryError(InputError):
    """A trajectory file or pose array is malformed (columns, non-finite values, lengths)."""


class EvaluationError(InputError):
    """Two trajectories cannot be compared (no matching stamps, too few poses for the metric)."""


class IntrinsicsError(InputError):
    """No usable camera for an export: none is known and the focal fitted to the points is
    implausible (the message says how to pass a calibration)."""


class StateError(KVTrackerError, RuntimeError):
    """The call is not allowed in the tracker's current state."""


class IllegalTransitionError(StateError):
    """A state transition that the transition table does not contain (always a bug)."""


class ModelError(KVTrackerError):
    """A model could not be built or loaded."""


class WeightsNotFoundError(ModelError, FileNotFoundError):
    """Weights could not be found locally nor downloaded."""


class CheckpointMismatchError(ModelError):
    """A checkpoint's keys or shapes do not match the model.

    ``missing``, ``unexpected`` and ``shape_mismatches`` list the offending keys.
    """

    def __init__(
        self,
        message: str,
        *,
        missing: list[str] | None = None,
        unexpected: list[str] | None = None,
        shape_mismatches: list[tuple[str, tuple[int, ...], tuple[int, ...]]] | None = None,
    ) -> None:
        super().__init__(message)
        self.missing = list(missing or [])
        self.unexpected = list(unexpected or [])
        self.shape_mismatches = list(shape_mismatches or [])


class CacheError(KVTrackerError, ValueError):
    """The KV cache was used inconsistently (layout, capacity, unknown keyframe)."""


class OutputError(KVTrackerError, OSError):
    """An output file or folder cannot be written (missing folder, no permission, a folder
    where a file should go, disk full)."""


class BackendError(KVTrackerError):
    """A backend failed or cannot serve the request."""


class CompileError(BackendError):
    """``torch.compile`` cannot be used for the tracking step (unsupported Python or platform, no
    C++ compiler, or the compilation failed) and no eager fallback was asked for."""


class BackendMismatchError(BackendError):
    """Two backends (or a backend and a cache/map) have different fingerprints or layouts."""


class MappingFailedError(BackendError):
    """A mapping pass (bootstrap or keyframe rebuild) failed: the backend raised (the original
    exception is ``__cause__``) or returned non-finite output. The tracker keeps its current map,
    reports the failure (event, ``MapStatus``) and retries later; it never raises this from
    ``push_frame``."""


class TrackingFailedError(BackendError):
    """Tracking one frame failed: the backend raised (``__cause__``) or returned a non-finite pose
    or confidence. ``push_frame`` returns it in ``FrameResult.error`` instead of raising."""


class MissingDependencyError(BackendError, ImportError):
    """An optional dependency is missing; the message names the extra to install (``extra``,
    e.g. ``"ros"``; :func:`install_command` says how to install it)."""

    def __init__(self, message: str, *, extra: str | None = None, hint: str | None = None) -> None:
        super().__init__(message, hint=hint)
        self.extra = extra

    @classmethod
    def for_extra(cls, extra: str, what: str) -> MissingDependencyError:
        """``what`` (e.g. "writing ROS 2 bags needs rosbags") plus how to install ``extra``."""
        return cls(f"{what}: {install_command(extra)}", extra=extra)


# The packages of each optional extra (pyproject.toml's [project.optional-dependencies]; a test
# keeps the two equal): the install command names them, because the package is not on PyPI and
# `pip install kvtracker-sdk[ros]` finds nothing.
EXTRA_PACKAGES: dict[str, tuple[str, ...]] = {
    "onnx": ("onnxruntime>=1.17", "onnx>=1.15", "onnxscript>=0.1", "onnx-ir>=1.0"),
    "openvino": ("openvino>=2024.0",),
    "hub": ("huggingface_hub>=0.20",),
    "viz": ("matplotlib>=3.7", "rerun-sdk>=0.18"),
    "ray": ("ray>=2.40", "pyyaml>=6"),
    "yaml": ("pyyaml>=6.0",),
    "view": ("viser>=1.0",),
    "ros": ("rosbags>=0.10",),
    "colmap": ("pycolmap>=3.10",),
    "docs": ("mkdocs>=1.6", "mkdocstrings[python]>=0.26"),
}


def install_command(extra: str) -> str:
    """How to install an optional extra, in a form that works from a clone of the repository
    and anywhere else: ``pip install -e ".[ros]"`` in the clone, or its packages directly."""
    packages = " ".join(f"'{p}'" for p in EXTRA_PACKAGES.get(extra, ()))
    direct = f" (or: pip install {packages})" if packages else ""
    return f'install the [{extra}] extra: pip install -e ".[{extra}]" in your kvtracker-sdk clone{direct}'


class MapError(KVTrackerError):
    """Base class of map-file errors."""


class MapFormatError(MapError):
    """The file is not a kvtracker map, or its header is malformed."""


class MapVersionError(MapError):
    """The map's format version is not supported by this SDK (too old or too new)."""


class MapModelMismatchError(MapError):
    """The map was made by another model, model family or resolution than the backend's."""


class MapCorruptedError(MapError):
    """The map's tensor data does not match its checksums or declared sizes."""


class MapPreprocessingError(MapError):
    """A map's keyframes were prepared by another preprocessing than new keyframes would be (e.g.
    a map saved with the SDK's earlier ``legacy-area-floor`` preprocessing): extending it would
    mix two input pipelines in one mapping pass.
    Tracking against it works; extending needs an explicit ``rebuild=True`` when loading."""


class MapIOError(MapError, OSError):
    """A map file cannot be read or written (missing, permission denied, disk full)."""

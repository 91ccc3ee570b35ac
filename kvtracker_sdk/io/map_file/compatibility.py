"""Can this map run here? One answer, for every load path: this backend, config and camera.

:func:`map_compatibility` reads only a map's header (:class:`MapInfo`), so a load asks it before
any tensor byte is read. Its answer is a :class:`MapCompatibility`: whether the map may run, why
not (each reason a :class:`MapMismatch` naming the typed error a load raises for it), the tracker
configuration it runs under, and whether the session's camera agrees with the saved one.

What is checked, in the order a load reports the first failure:

1. the model (:attr:`MismatchKind.MODEL`): the backend must compute the function that made the
   map — family, config hash, weights fingerprint, cache layout and tokenisation — at the
   map's model input size (H, W); the runtime, device and dtype may differ;
2. for a tracker (a :class:`TrackerRequest`):
   the preprocessing that prepared the keyframe images must be known (or be the backend's own);
   the configuration — the saved one, a replacement ``TrackerConfig``, or changes to the saved
   one — must be valid, in the map's mode, at the map's resolution side (its keyframe images and
   K/V exist at one model input size; object maps hold masked keyframes).

A camera that differs from the saved one is not a refusal (the networks take no intrinsics as
input) but is reported (``camera_agrees``): the map's geometry was made by the saved camera.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from kvtracker_sdk.cache.backend_info import BackendInfo
from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.errors import (
    ConfigError,
    KVTrackerError,
    MapFormatError,
    MapModelMismatchError,
    MapVersionError,
)
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.io.map_file.map_format import MapInfo
from kvtracker_sdk.preprocess import PREPROCESSINGS

__all__ = [
    "ConfigOverride",
    "MapCompatibility",
    "MapMismatch",
    "MismatchKind",
    "TrackerRequest",
    "cameras_agree",
    "map_compatibility",
]

# The configuration a tracker asks a map to run under: None keeps the saved one, a
# ``TrackerConfig`` replaces it, a mapping changes some of its fields (``TrackerConfig.updated``).
ConfigOverride = TrackerConfig | Mapping[str, Any] | None

# Two cameras agree when their image sizes are equal, focal lengths within 1 % and principal
# points within 1 % of the image size: closer than any calibration of one camera differs.
_CAMERA_RTOL = 0.01


class MismatchKind(enum.Enum):
    """Why a map cannot run with a backend and configuration."""

    MODEL = "model"  # another model, cache layout, tokenisation or model input size
    PREPROCESSING = "preprocessing"  # keyframes prepared by a preprocessing this SDK lacks
    CONFIG = "config"  # the requested configuration is not a configuration
    SAVED_CONFIG = "saved_config"  # the saved configuration cannot be used as saved
    MODE = "mode"  # the configuration's tracking mode is not the map's
    RESOLUTION = "resolution"  # the configuration's resolution side is not the map's


@dataclass(frozen=True)
class MapMismatch:
    """One reason a map cannot run: its kind, the message a load raises and that error's type.
    ``cause``: the error that revealed it, chained when raised; raised itself when it is this
    very error (an invalid configuration change: its message and hint as the config made them)."""

    kind: MismatchKind
    message: str
    error: type[KVTrackerError]
    cause: BaseException | None = field(default=None, compare=False)

    def exception(self) -> KVTrackerError:
        if isinstance(self.cause, self.error) and str(self.cause) == self.message:
            return self.cause
        return self.error(self.message)


@dataclass(frozen=True)
class TrackerRequest:
    """What a tracker asks of a map beyond its model: the configuration (see
    ``ConfigOverride``), the name of the preprocessing its backend declares (known even when
    this SDK does not register it) and the session's camera (None: unknown)."""

    config: ConfigOverride = None
    preprocessing: str | None = None
    camera: Camera | None = None


@dataclass(frozen=True)
class MapCompatibility:
    """The answer of :func:`map_compatibility`.

    ``mismatches``: every reason found, in checking order (empty: the map may run).
    ``config``: for a tracker request, the configuration the map runs under (None when the
    request was refused before one could be chosen, and for a model-only question).
    ``camera_agrees``: False when the request's camera and the saved one are both known and
    differ (see :func:`cameras_agree`).
    """

    mismatches: tuple[MapMismatch, ...] = ()
    config: TrackerConfig | None = None
    camera_agrees: bool = True

    @property
    def ok(self) -> bool:
        return not self.mismatches

    def raise_if_refused(self) -> None:
        """Raise the first mismatch's typed error (chained to its cause), if there is one."""
        if self.mismatches:
            first = self.mismatches[0]
            error = first.exception()
            if error is first.cause:
                raise error
            raise error from first.cause


def _describe(backend: BackendInfo) -> str:
    return f"model {backend.model!r} (family {backend.family}, fingerprint {backend.fingerprint})"


def _model_mismatch(
    info: MapInfo, backend: BackendInfo, resolution: tuple[int, int] | None
) -> MapMismatch | None:
    saved = info.backend
    differences = [
        f"{what} {mine!r} vs {theirs!r}"
        for what, mine, theirs in (
            ("family", saved.family, backend.family),
            ("config hash", saved.config_hash, backend.config_hash),
            ("weights fingerprint", saved.weights_fingerprint, backend.weights_fingerprint),
            ("cache layout", saved.layout, backend.layout),
            ("patch size", saved.patch_size, backend.patch_size),
            (
                "extra tokens per frame",
                saved.extra_tokens_per_frame,
                backend.extra_tokens_per_frame,
            ),
            ("resolution", info.resolution, tuple(resolution or info.resolution)),
        )
        if mine != theirs
    ]
    if not differences:
        return None
    return MapMismatch(
        MismatchKind.MODEL,
        f"map made by {_describe(saved)} at {info.resolution[0]}x{info.resolution[1]} cannot "
        f"be used with {_describe(backend)}: " + "; ".join(differences) + " (map vs backend)",
        MapModelMismatchError,
    )


def _preprocessing_mismatch(info: MapInfo, declared: str | None, source: str) -> MapMismatch | None:
    if info.preprocessing in PREPROCESSINGS or info.preprocessing == declared:
        return None
    return MapMismatch(
        MismatchKind.PREPROCESSING,
        f"{source}: its frames were prepared by {info.preprocessing!r}, which this SDK "
        f"does not know (known: {sorted(PREPROCESSINGS)}); upgrade kvtracker-sdk",
        MapVersionError,
    )


def _saved_config(info: MapInfo, source: str) -> TrackerConfig | MapMismatch:
    try:
        config = TrackerConfig.from_dict(dict(info.tracker_config))
    except ConfigError as exc:  # e.g. a map from a newer SDK with more settings
        return MapMismatch(
            MismatchKind.SAVED_CONFIG,
            f"{source}: the tracker config saved in the map is not valid for this SDK ({exc}); "
            "pass config=TrackerConfig(...) to choose one",
            MapFormatError,
            exc,
        )
    if config.mode.value != info.mode:  # both come from an older file: it contradicts itself
        return MapMismatch(
            MismatchKind.SAVED_CONFIG,
            f"{source}: the header says {info.mode} mode, the saved tracker config "
            f"{config.mode.value} mode",
            MapFormatError,
        )
    return config


def _requested_config(
    info: MapInfo, override: ConfigOverride, source: str
) -> TrackerConfig | MapMismatch:
    """The configuration asked for, before the map's mode and resolution are checked."""
    if isinstance(override, TrackerConfig):
        return override
    if override is not None and not isinstance(override, Mapping):
        return MapMismatch(
            MismatchKind.CONFIG,
            f"config must be a TrackerConfig, a dict or None, not {override!r}",
            ConfigError,
        )
    config = _saved_config(info, source)
    if override and isinstance(config, TrackerConfig):
        try:
            return config.updated(**override)
        except ConfigError as exc:
            return MapMismatch(MismatchKind.CONFIG, str(exc), type(exc), exc)
    return config


def fits_side(resolution: tuple[int, int], side: int, patch: int) -> bool:
    """Whether any preprocessing (``kvtracker_sdk.preprocess.sizing``) could give (H, W) at a
    resolution ``side`` — a necessary condition that holds for every pipeline, so a genuine map is
    never refused. Upper bound: at most side² pixels for Pi3's and the legacy sizing (the legacy
    one may exceed it only with a side clamped to one patch), (side + patch/2)² for DA3's longest
    side. Lower bound: Pi3's and the legacy sizing round or floor each side by less than a patch
    below the budget, so (H + patch)(W + patch) > side²; DA3's longest side is within patch/2 of
    ``side``."""
    height, width = resolution
    below = height * width <= (side + patch) ** 2 or min(height, width) <= patch
    longest = max(height, width)
    above = (height + patch) * (width + patch) > side * side or 2 * longest >= 2 * side - patch
    return below and above


def _run_config(
    info: MapInfo, override: ConfigOverride, source: str
) -> TrackerConfig | MapMismatch:
    """The configuration the map runs under, or why there is none: the mode must be the map's,
    and the resolution side the one its keyframes were made at."""
    config = _requested_config(info, override, source)
    if isinstance(config, MapMismatch):
        return config
    if config.mode.value != info.mode:
        return MapMismatch(
            MismatchKind.MODE,
            f"{source} was saved in {info.mode} mode; the tracker is configured for "
            f"{config.mode.value} mode",
            ConfigError,
        )
    saved_side = info.tracker_config.get("resolution")
    if not isinstance(saved_side, int):
        return config
    (height, width), patch = info.resolution, info.backend.patch_size
    if not fits_side(info.resolution, saved_side, patch):
        return MapMismatch(
            MismatchKind.SAVED_CONFIG,
            f"{source}: its saved tracker config has resolution {saved_side}, which cannot give "
            f"its {height}x{width} keyframes (patch {patch})",
            MapFormatError,
        )
    if config.resolution is None:
        config = config.updated(resolution=saved_side)  # unset: the map's
    if saved_side != config.resolution:
        return MapMismatch(
            MismatchKind.RESOLUTION,
            f"{source} was built at resolution {saved_side} (model input {height}x{width}); "
            f"the tracker is configured for resolution {config.resolution}",
            MapModelMismatchError,
        )
    return config


def cameras_agree(saved: Camera | None, given: Camera | None) -> bool:
    """True unless both cameras are known and differ (once undistorted): another image size, a
    focal length off by more than 1 %, or a principal point off by more than 1 % of the image
    size."""
    if saved is None or given is None:
        return True
    given, saved = given.undistorted(), saved.undistorted()
    return (
        saved.size == given.size
        and abs(given.fx / saved.fx - 1.0) <= _CAMERA_RTOL
        and abs(given.fy / saved.fy - 1.0) <= _CAMERA_RTOL
        and abs(given.cx - saved.cx) <= _CAMERA_RTOL * saved.width
        and abs(given.cy - saved.cy) <= _CAMERA_RTOL * saved.height
    )


def map_compatibility(
    info: MapInfo,
    backend: BackendInfo,
    *,
    resolution: tuple[int, int] | None = None,
    tracker: TrackerRequest | None = None,
    source: str = "map",
) -> MapCompatibility:
    """Whether the map whose header is ``info`` can run with ``backend`` (and, with
    ``tracker``, under that request's configuration and camera); ``resolution`` (H, W), if given,
    must equal the map's model input size. ``source`` names the map in messages.

    Reads nothing but ``info``; raises nothing (``MapCompatibility.raise_if_refused`` does).
    """
    mismatches = [m for m in (_model_mismatch(info, backend, resolution),) if m is not None]
    if tracker is None:
        return MapCompatibility(tuple(mismatches))
    if problem := _preprocessing_mismatch(info, tracker.preprocessing, source):
        mismatches.append(problem)
    config = _run_config(info, tracker.config, source)
    if isinstance(config, MapMismatch):
        mismatches.append(config)
    runs_under = config if isinstance(config, TrackerConfig) and not mismatches else None
    return MapCompatibility(
        tuple(mismatches), runs_under, cameras_agree(info.camera, tracker.camera)
    )

"""``TrackerConfig``: every knob of the tracker, frozen and validated (pydantic v2).

Each default that comes from the KV-Tracker paper (Taher et al., "KV-Tracker: Real-Time Pose
Tracking with Transformers", CVPR 2026) or from the SDK's design document
(``../shared/docs/design.md``) names its source in the field's docstring; the rest are SDK
choices and say why.

Build a config with keyword arguments or a nested dict; invalid values raise
:class:`~kvtracker_sdk.errors.ConfigError` (pydantic's ``ValidationError`` is wrapped)::

    TrackerConfig(mode="object", keyframing={"view_angle_deg": 15.0})
    TrackerConfig.from_dict(json.loads(text))
    config.updated(threading={"async_mapping": True})  # a validated copy

Sections are frozen too, so a config can be shared between threads and stored in a map file
(``config.to_dict()`` is JSON-ready).
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.types import HeadSet

__all__ = [
    "BudgetConfig",
    "DebugConfig",
    "EvictionPolicy",
    "KeyframingConfig",
    "MapCompactionConfig",
    "OBJECT_MAX_KEYFRAMES",
    "ObjectConfig",
    "ObjectKeyframeRule",
    "ObjectPreprocessing",
    "RejectionConfig",
    "RelocalizationConfig",
    "ThreadingConfig",
    "TimeoutPolicy",
    "TrackerConfig",
    "TrackingMode",
]


class TrackingMode(str, enum.Enum):
    """Scene tracking (the camera in a static scene) or object tracking (a masked object)."""

    SCENE = "scene"
    OBJECT = "object"


class EvictionPolicy(str, enum.Enum):
    """Which keyframe leaves the map when the budget is full (keyframe 0 never does)."""

    OLDEST = "oldest"  # first in, first out
    REDUNDANT = "redundant"  # the keyframe whose pose is closest to another keyframe's


class TimeoutPolicy(str, enum.Enum):
    """What relocalisation does after ``timeout_frames`` frames without recovering."""

    STAY = "stay"  # keep relocalising against the map (the map may come back into view)
    RESET = "reset"  # drop the map, back to INIT
    NEW_MAP = "new_map"  # drop the map and bootstrap a new one from the current frame


class ObjectPreprocessing(str, enum.Enum):
    """How object mode restricts the model's input to the object."""

    MASK = "mask"  # pixels outside the mask (or bbox) become black
    CROP = "crop"  # crop to the mask's (or bbox's) box dilated by ``crop_margin_px``


class ObjectKeyframeRule(str, enum.Enum):
    """When object mode adds a keyframe, judged from the object centre (``tracking/mapping/keyframes.py``)."""

    VIEW_DIRECTION = "view_direction"  # the angle between view directions exceeds the threshold
    AZIMUTH_ELEVATION = "azimuth_elevation"  # the paper's: |Δazimuth| or |Δelevation|, each alone


# Object mode's default keyframe budget (KV-Tracker paper: 50-60 keyframes usually cover an
# object; one 10-degree orbit alone takes 36).
OBJECT_MAX_KEYFRAMES = 60
SCENE_MAX_KEYFRAMES = 32


def _error_lines(error: ValidationError, prefix: tuple[object, ...] = ()) -> list[str]:
    """One line per invalid value, with the full dotted path (nested sections flattened)."""
    lines: list[str] = []
    for item in error.errors():
        loc = prefix + tuple(item["loc"])
        inner = item.get("ctx", {}).get("error")
        if isinstance(inner, ConfigError) and isinstance(inner.__cause__, ValidationError):
            lines.extend(_error_lines(inner.__cause__, loc))  # a nested section's own __init__
            continue
        path = ".".join(str(p) for p in loc) or "<root>"
        lines.append(f"{path}: {item['msg']} (got {item.get('input')!r})")
    return lines


class _Section(BaseModel):
    """Frozen, strict-keys base: unknown keys are errors, not silently ignored.

    ``__init__`` re-raises pydantic's ValidationError as ConfigError, for top-level configs and for
    sections built on their own alike.
    """

    model_config = ConfigDict(
        frozen=True, extra="forbid", validate_default=True, use_attribute_docstrings=True
    )

    def __init__(self, **data: Any) -> None:
        try:
            super().__init__(**data)
        except ValidationError as exc:
            details = "; ".join(_error_lines(exc))
            raise ConfigError(f"invalid {type(self).__name__}: {details}") from exc

    def __setattr__(self, name: str, value: Any) -> None:
        raise ConfigError(
            f"{type(self).__name__} is frozen; make a changed copy with TrackerConfig.updated(...)"
        )


class BudgetConfig(_Section):
    """Upper bounds on the map; when a new keyframe would exceed them, one is evicted."""

    max_keyframes: int | None = Field(default=SCENE_MAX_KEYFRAMES, ge=2)
    """At most this many keyframes (None: no count limit). Scene mode: 32, an SDK default, not from
    the paper: a rebuild costs O((N·M)²) in the number of keyframes N, so the map needs a bound.
    Object mode: 60 unless set (``OBJECT_MAX_KEYFRAMES``; KV-Tracker paper: 50-60 keyframes
    usually cover an object)."""

    max_cache_bytes: int | None = Field(default=None, gt=0)
    """At most this many bytes of K/V (None: no byte limit). Full Pi3 at d=308 in fp32 needs about
    72 MB per keyframe (489 tokens x 18 layers x 16 heads x 64 dims x K,V x 4 bytes). A budget below
    two keyframes keeps only keyframe 0 (design doc: budget "count or bytes")."""

    eviction: EvictionPolicy = EvictionPolicy.REDUNDANT
    """Which keyframe to drop; keyframe 0 (the world anchor) is never dropped (design doc)."""


class KeyframingConfig(_Section):
    """When a tracked frame becomes a keyframe."""

    interval_frames: int = Field(default=50, ge=1)
    """Scene mode: a keyframe every this many frames (KV-Tracker paper, scene tracking)."""

    view_angle_deg: float = Field(default=10.0, gt=0.0, lt=180.0)
    """Object mode: the threshold τ of ``object_rule`` in degrees (KV-Tracker paper: 10°)."""

    object_rule: ObjectKeyframeRule = ObjectKeyframeRule.VIEW_DIRECTION
    """Object mode: a keyframe when the angle between the unit directions from the object centre
    to the camera and to *every* keyframe exceeds ``view_angle_deg`` (``view_direction``, the
    default: one 10° ring adds ~36 keyframes, a second ring 30° higher ~31, an orbit near the pole
    ~1). ``azimuth_elevation`` is the KV-Tracker paper's rule as written (min |Δazimuth| or min
    |Δelevation| over the keyframes, each axis alone): it adds no keyframe on a second ring and
    one per 10° of azimuth on an orbit near the pole, where views differ by less than 10°.
    Compared on synthetic orbits by ``benchmarks/object_keyframe_rules.py``."""

    budget: BudgetConfig = BudgetConfig()


class RejectionConfig(_Section):
    """Undo a rebuild whose new keyframe the model is unsure about."""

    enabled: bool = True
    ratio: float = Field(default=0.6, gt=0.0, le=1.0)
    """Reject when the new keyframe's (masked) mean confidence is below ``ratio`` x keyframe 0's
    in the same mapping pass (KV-Tracker paper: 0.6)."""

    retry_after_frames: int = Field(default=15, ge=1)
    """Frames to wait after a rejected candidate before proposing another (SDK choice: while the
    view stays bad, object mode would otherwise rebuild the map on every frame)."""


class RelocalizationConfig(_Section):
    """Confidence-based loss detection and recovery (SDK defaults; the paper does not fix them)."""

    confidence_threshold: float = Field(default=0.5, gt=0.0, le=1.0)
    """A tracked frame is confident when its (masked) mean confidence is at least this fraction of
    keyframe 0's. Relative, like the paper's rejection rule, so that it does not depend on one
    model's absolute confidence scale."""

    lost_after: int = Field(default=3, ge=1)
    """Consecutive low-confidence frames before TRACKING -> RELOCALIZING (0.1 s at 30 Hz)."""

    recover_after: int = Field(default=3, ge=1)
    """Consecutive confident frames before RELOCALIZING -> TRACKING."""

    timeout_frames: int | None = Field(default=300, ge=1)
    """Frames in RELOCALIZING before ``timeout_policy`` acts (10 s at 30 Hz; None: never)."""

    timeout_policy: TimeoutPolicy = TimeoutPolicy.STAY


class ObjectConfig(_Section):
    """Object-mode preprocessing of each frame (design doc: "mask -> black background, or the
    mask's bbox dilated by N px")."""

    preprocessing: ObjectPreprocessing = ObjectPreprocessing.MASK
    crop_margin_px: int = Field(default=50, ge=0)
    """Dilation of the crop box, in input-image pixels (KV-Tracker paper / design doc: 50 px)."""

    search_frames: int = Field(default=90, ge=1)
    """A loaded object map is relocalised against the whole frame (no mask or box needed); after
    this many frames without finding the object (3 s at 30 Hz) the reason becomes
    ``OBJECT_NOT_FOUND``: the app should give the object's mask or box again."""


class ThreadingConfig(_Section):
    """Where map rebuilds run."""

    async_mapping: bool = False
    """Rebuild on a worker thread while ``push_frame`` keeps tracking against the previous map; the
    new map is swapped in atomically at a later ``push_frame`` (design doc, optional)."""


class MapCompactionConfig(_Section):
    """Smaller maps and cheaper keyframes (``kvtracker_sdk.cache.pruning``). Every
    switch is off by default: the accuracy cost on real weights is unmeasured (``benchmarks/README.md``,
    "Token pruning")."""

    keep_ratio: float | None = Field(default=None, gt=0.0, le=1.0)
    """Token pruning once per rebuild: the fraction of each global layer's cached tokens kept,
    chosen by key redundancy; keyframe 0 and every frame's register/camera tokens are always kept.
    None: keep every token."""

    prune_score: Literal["key_diversity", "uniform"] = "key_diversity"
    """Which tokens pruning drops: ``key_diversity`` (InfiniteVGGT: keys closest to the layer's
    mean key first) or ``uniform`` (an evenly spread subset of every frame's patches)."""

    object_tokens: bool = False
    """Object mode with mask preprocessing: drop the cached tokens of patches outside each
    keyframe's dilated object mask (black in the masked input)."""

    object_dilation_patches: int = Field(default=1, ge=0)
    """Dilation of the object mask before dropping tokens, in patches (14 px)."""

    incremental_keyframes: bool = False
    """Add a keyframe by one tracking pass against the map, keeping the frame's K/V (the other
    keyframes' K/V and poses stay as they are) instead of re-running the mapping pass over all
    keyframes. PyTorch backends only (others rebuild)."""

    rebuild_every: int = Field(default=4, ge=1)
    """With incremental keyframes: a full rebuild after this many insertions."""

    rebuild_below: float = Field(default=0.8, gt=0.0, le=1.0)
    """With incremental keyframes: a candidate whose mean confidence in its insertion pass is
    below this fraction of keyframe 0's gets a full rebuild instead."""


class DebugConfig(_Section):
    """Switches for measuring what a component buys; keep the defaults in production."""

    gauge_alignment: bool = True
    """Align every rebuild to the previous map by Sim(3). Off: poses stay in each mapping pass's
    own raw frame and scale (the world frame jumps on every rebuild)."""


class TrackerConfig(_Section):
    """Everything the ``Tracker`` can be told. Frozen; see the module docstring for construction."""

    mode: TrackingMode = TrackingMode.SCENE
    resolution: Literal[224, 308, 504, 518] | None = None
    """Model input side d; its meaning is the model family's official preprocessing
    (``kvtracker_sdk.preprocess``), aspect kept, sides multiples of the patch size (14):

    * Pi3: a pixel budget, at most d² pixels, as KV-Tracker prepares frames (KV-Tracker paper:
      224, 308 or 518). 640x480 frames become 196x252 at 224, 266x350 at 308, 448x588 at 518.
    * Depth Anything 3: the longest side, as DA3's ``upper_bound_resize`` (its ``process_res``).
      640x480 frames become 168x224 at 224, 378x504 at 504.

    None (default): the family's own default, 308 for Pi3 (KV-Tracker's real-time setting) and
    504 for DA3 (DA3's default); the tracker stores the value it resolved in its config."""

    keyframing: KeyframingConfig = KeyframingConfig()
    rejection: RejectionConfig = RejectionConfig()
    relocalization: RelocalizationConfig = RelocalizationConfig()
    object: ObjectConfig = ObjectConfig()
    threading: ThreadingConfig = ThreadingConfig()
    compaction: MapCompactionConfig = MapCompactionConfig()
    cache_dtype: Literal["backend", "int8", "fp8"] = "backend"
    """How the map's K/V are kept between rebuilds and in saved maps: ``backend``
    (default) in the backend's dtype (fp32 or bf16); ``int8`` or ``fp8`` (e4m3) quantised with a
    scale per token and head, ~1.94x smaller than bf16 (K/V), dequantised one layer at a time while
    tracking (``kvtracker_sdk.cache.quantization``). Off by default: on the golden reduced models
    int8 moves poses far less than the bf16 backend does (``benchmarks/README.md``, "Compact maps:
    quantised K/V"), but the cost on real weights is unmeasured. PyTorch backends only
    (``OnnxBackend`` refuses quantised caches)."""

    heads: HeadSet = HeadSet.CONFIDENCE
    """Heads computed per tracked frame. CONFIDENCE is the default because loss detection needs
    confidence; CAMERA is faster but then every frame counts as confident."""

    debug: DebugConfig = DebugConfig()

    @model_validator(mode="before")
    @classmethod
    def _object_mode_defaults(cls, data: Any) -> Any:
        """Object mode sizes the keyframe budget for an object when the caller left it unset."""
        if not isinstance(data, Mapping) or str(_value(data.get("mode"))) != "object":
            return data
        keyframing = data.get("keyframing")
        if isinstance(keyframing, KeyframingConfig):
            section = keyframing.budget
            if "max_keyframes" in section.model_fields_set or "budget" in keyframing.model_fields_set:
                return data
            keyframing = keyframing.model_dump(mode="json", exclude={"budget"})
        elif keyframing is None:
            keyframing = {}
        elif not isinstance(keyframing, Mapping):
            return data  # not a section: validation reports it
        budget_data = keyframing.get("budget", {})
        if isinstance(budget_data, BudgetConfig):
            if "max_keyframes" in budget_data.model_fields_set:
                return data
            budget_data = budget_data.model_dump(mode="json", exclude={"max_keyframes"})
        if not isinstance(budget_data, Mapping) or "max_keyframes" in budget_data:
            return data
        budget = {**budget_data, "max_keyframes": OBJECT_MAX_KEYFRAMES}
        return {**data, "keyframing": {**keyframing, "budget": budget}}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> TrackerConfig:
        """Validate a nested dict (e.g. from JSON or a map file); raises ConfigError."""
        if not isinstance(data, Mapping):
            raise ConfigError(f"a config must be a mapping, got {type(data).__name__}")
        return cls(**dict(data))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready nested dict (enums as their values); ``from_dict`` reads it back."""
        return self.model_dump(mode="json")

    def updated(self, **changes: Any) -> TrackerConfig:
        """A validated copy with ``changes``; nested sections merge (``keyframing={...}``)."""
        data = self.to_dict()
        if "mode" in changes and str(_value(changes["mode"])) != self.mode.value:
            # a mode switch takes the new mode's keyframe budget unless it was changed by hand
            budget = data["keyframing"]["budget"]
            if budget["max_keyframes"] in (SCENE_MAX_KEYFRAMES, OBJECT_MAX_KEYFRAMES):
                budget["max_keyframes"] = (
                    OBJECT_MAX_KEYFRAMES if str(_value(changes["mode"])) == "object"
                    else SCENE_MAX_KEYFRAMES
                )
        for key, value in changes.items():
            if isinstance(value, BaseModel):
                value = value.model_dump(mode="json")
            if isinstance(value, Mapping) and isinstance(data.get(key), dict):
                data[key] = _merge(data[key], value)
            else:
                data[key] = value
        return TrackerConfig.from_dict(data)


def _value(value: Any) -> Any:
    """An enum's value, anything else as is (modes arrive as strings or ``TrackingMode``)."""
    return value.value if isinstance(value, enum.Enum) else value


def _merge(base: dict[str, Any], changes: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in changes.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out

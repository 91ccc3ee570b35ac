"""TrackerConfig: paper defaults, validation errors as ConfigError, frozen sections, round trips."""

from __future__ import annotations

import json

import pytest

from kvtracker_sdk.config import (
    BudgetConfig,
    EvictionPolicy,
    KeyframingConfig,
    ObjectConfig,
    ObjectKeyframeRule,
    ObjectPreprocessing,
    RejectionConfig,
    RelocalizationConfig,
    TimeoutPolicy,
    TrackerConfig,
    TrackingMode,
)
from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.types import HeadSet


def test_defaults_are_the_paper_and_design_values() -> None:
    config = TrackerConfig()
    assert config.mode is TrackingMode.SCENE
    assert config.resolution is None  # the family's own: Pi3 308, DA3 504 (test_frame_input)
    assert config.keyframing.interval_frames == 50
    assert config.keyframing.view_angle_deg == 10.0
    assert config.rejection.ratio == 0.6
    assert config.object.preprocessing is ObjectPreprocessing.MASK
    assert config.object.crop_margin_px == 50
    assert config.heads is HeadSet.CONFIDENCE  # loss detection needs confidence
    assert config.threading.async_mapping is False
    assert config.debug.gauge_alignment is True


def test_object_mode_sizes_the_budget_for_an_object_unless_told() -> None:
    assert TrackerConfig().keyframing.budget.max_keyframes == 32
    obj = TrackerConfig(mode="object")
    assert obj.keyframing.budget.max_keyframes == 60  # paper: 50-60 keyframes cover an object
    assert obj.keyframing.object_rule is ObjectKeyframeRule.VIEW_DIRECTION
    assert TrackerConfig(mode=TrackingMode.OBJECT, keyframing={"view_angle_deg": 15.0}
                         ).keyframing.budget.max_keyframes == 60
    told = {"keyframing": {"budget": {"max_keyframes": 12}}}
    assert TrackerConfig(mode="object", **told).keyframing.budget.max_keyframes == 12
    section = KeyframingConfig(budget=BudgetConfig(max_keyframes=40))
    assert TrackerConfig(mode="object", keyframing=section).keyframing.budget.max_keyframes == 40
    assert TrackerConfig(mode="object", keyframing=KeyframingConfig()
                         ).keyframing.budget.max_keyframes == 60
    # switching modes takes the new mode's default, a hand-set budget stays
    assert TrackerConfig().updated(mode="object").keyframing.budget.max_keyframes == 60
    assert obj.updated(mode="scene").keyframing.budget.max_keyframes == 32
    assert TrackerConfig(**told).updated(mode="object").keyframing.budget.max_keyframes == 12
    assert TrackerConfig.from_dict(obj.to_dict()) == obj
    paper = TrackerConfig(mode="object", keyframing={"object_rule": "azimuth_elevation"})
    assert paper.keyframing.object_rule is ObjectKeyframeRule.AZIMUTH_ELEVATION


@pytest.mark.parametrize(
    ("section", "field", "source"),
    [
        (KeyframingConfig, "interval_frames", "KV-Tracker paper"),
        (KeyframingConfig, "view_angle_deg", "KV-Tracker paper"),
        (BudgetConfig, "max_keyframes", "KV-Tracker paper"),
        (RejectionConfig, "ratio", "KV-Tracker paper"),
        (ObjectConfig, "crop_margin_px", "KV-Tracker paper"),
        (TrackerConfig, "resolution", "KV-Tracker paper"),
        (BudgetConfig, "eviction", "design doc"),
        (RelocalizationConfig, "confidence_threshold", "keyframe 0"),
    ],
)
def test_paper_defaults_name_their_source(section: type, field: str, source: str) -> None:
    description = section.model_fields[field].description  # field docstrings (pydantic)
    assert description is not None and source in description


@pytest.mark.parametrize(
    "kwargs",
    [
        {"resolution": 300},
        {"mode": "tunnel"},
        {"keyframing": {"interval_frames": 0}},
        {"keyframing": {"view_angle_deg": -1.0}},
        {"keyframing": {"budget": {"max_keyframes": 1}}},
        {"keyframing": {"budget": {"max_cache_bytes": 0}}},
        {"keyframing": {"budget": {"eviction": "random"}}},
        {"rejection": {"ratio": 1.5}},
        {"rejection": {"ratio": 0.0}},
        {"relocalization": {"lost_after": 0}},
        {"relocalization": {"recover_after": -2}},
        {"relocalization": {"timeout_policy": "panic"}},
        {"relocalization": {"confidence_threshold": 2.0}},
        {"object": {"crop_margin_px": -5}},
        {"heads": "everything"},
        {"unknown_section": {}},
        {"keyframing": {"interval": 50}},  # misspelt key: an error, never silently ignored
        {"keyframing": {"object_rule": "azimuth"}},
    ],
)
def test_invalid_values_raise_config_error(kwargs: dict) -> None:
    with pytest.raises(ConfigError) as info:
        TrackerConfig(**kwargs)
    first_key = next(iter(kwargs))
    assert first_key in str(info.value)  # the message names the offending path


def test_nested_error_path_is_flattened() -> None:
    with pytest.raises(ConfigError, match=r"keyframing\.budget\.max_keyframes"):
        TrackerConfig(keyframing={"budget": {"max_keyframes": 0}})


def test_sections_built_alone_raise_config_error_too() -> None:
    with pytest.raises(ConfigError, match="max_keyframes"):
        BudgetConfig(max_keyframes=1)


def test_configs_are_frozen() -> None:
    config = TrackerConfig()
    with pytest.raises(ConfigError, match="frozen"):
        config.resolution = 224  # type: ignore[misc]
    with pytest.raises(ConfigError, match="frozen"):
        config.keyframing.interval_frames = 3  # type: ignore[misc]


def test_updated_merges_nested_sections_and_validates() -> None:
    config = TrackerConfig(keyframing={"interval_frames": 30})
    changed = config.updated(keyframing={"budget": {"max_keyframes": 8}}, mode="object")
    assert changed.keyframing.interval_frames == 30  # kept
    assert changed.keyframing.budget.max_keyframes == 8
    assert changed.mode is TrackingMode.OBJECT
    assert config.keyframing.budget.max_keyframes == 32  # the original is untouched
    with pytest.raises(ConfigError):
        config.updated(relocalization={"lost_after": 0})


def test_json_round_trip() -> None:
    config = TrackerConfig(
        mode="object",
        resolution=518,
        keyframing={"budget": {"eviction": "oldest", "max_cache_bytes": 10**9}},
        relocalization={"timeout_policy": "new_map", "timeout_frames": None},
    )
    text = json.dumps(config.to_dict())
    again = TrackerConfig.from_dict(json.loads(text))
    assert again == config
    assert again.keyframing.budget.eviction is EvictionPolicy.OLDEST
    assert again.relocalization.timeout_policy is TimeoutPolicy.NEW_MAP


def test_from_dict_rejects_non_mappings() -> None:
    with pytest.raises(ConfigError):
        TrackerConfig.from_dict(["mode", "scene"])  # type: ignore[arg-type]

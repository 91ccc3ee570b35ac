"""Sizing plans: the official arithmetic's properties, for any frame size (hypothesis)."""

from __future__ import annotations

import cv2
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kvtracker_sdk.cache.keyframe_map import LEGACY_PREPROCESSING
from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.preprocess import (
    FAMILY_PREPROCESSING,
    LEGACY_AREA_FLOOR,
    PREPROCESSINGS,
    da3_upper_bound_plan,
    for_family,
    legacy_area_floor_plan,
    named,
    pi3_kvtracker_plan,
)
from kvtracker_sdk.preprocess.sizing import plan_output_size

SIDES = st.integers(min_value=14, max_value=4000)
RESOLUTIONS = st.sampled_from([224, 308, 504, 518])


@settings(max_examples=150, deadline=None)
@given(height=SIDES, width=SIDES, side=RESOLUTIONS)
def test_pi3_sides_are_patch_multiples_within_the_budget_and_keep_the_aspect(
    height: int, width: int, side: int
) -> None:
    plan = pi3_kvtracker_plan((height, width), side)
    out_h, out_w = plan_output_size((height, width), plan)
    assert out_h % 14 == 0 and out_w % 14 == 0 and out_h >= 14 and out_w >= 14
    rows, cols = out_h // 14, out_w // 14
    if rows * cols > 1:
        assert out_h * out_w <= side * side  # the d² budget holds
    aspect = width / height
    # each side is rounded (<= 1/2 patch) then the too-large side shrinks: within 1.5 patches
    if min(rows, cols) > 1 and 1 / 50 < aspect < 50:
        assert abs(out_w / out_h - aspect) / aspect <= 1.5 / min(rows, cols) + 1.5 / max(rows, cols)
    assert all(step.interpolation == cv2.INTER_LINEAR for step in plan) and len(plan) <= 1


@settings(max_examples=150, deadline=None)
@given(height=SIDES, width=SIDES, side=RESOLUTIONS)
def test_da3_longest_side_is_the_resolution_rounded_to_the_patch(
    height: int, width: int, side: int
) -> None:
    plan = da3_upper_bound_plan((height, width), side)
    out_h, out_w = plan_output_size((height, width), plan)
    assert out_h % 14 == 0 and out_w % 14 == 0 and min(out_h, out_w) >= 14
    assert abs(max(out_h, out_w) - side) <= 7  # longest side d, then the nearest multiple
    short = min(height, width) * side / max(height, width)
    assert abs(min(out_h, out_w) - short) <= 7.5 or min(out_h, out_w) == 14  # round, then round
    befores = [(height, width), *(s.size for s in plan)][: len(plan)]
    for step, before in zip(plan, befores, strict=True):
        grows = step.size[0] > before[0] or step.size[1] > before[1]
        assert step.interpolation == (cv2.INTER_CUBIC if grows else cv2.INTER_AREA)


@pytest.mark.parametrize(
    ("source", "side", "pi3", "da3"),
    [
        ((480, 640), 224, (196, 252), (168, 224)),
        ((480, 640), 308, (266, 350), (238, 308)),
        ((480, 640), 504, (434, 574), (378, 504)),
        ((480, 640), 518, (448, 588), (392, 518)),
        ((640, 480), 224, (252, 196), (224, 168)),
        ((259, 601), 224, (140, 336), (98, 224)),
    ],
)
def test_known_sizes(source: tuple[int, int], side: int, pi3: tuple, da3: tuple) -> None:
    assert for_family("pi3").model_size(source, side, 14) == pi3
    assert for_family("da3").model_size(source, side, 14) == da3


def test_da3_takes_two_steps_when_the_longest_side_does_not_round() -> None:
    # 640x480 at 308: 308x231 (area), then 231 -> 238 (a tie goes up; cubic since it grows)
    plan = da3_upper_bound_plan((480, 640), 308)
    assert [(s.size, s.interpolation) for s in plan] == [
        ((231, 308), cv2.INTER_AREA),
        ((238, 308), cv2.INTER_CUBIC),
    ]
    assert da3_upper_bound_plan((378, 504), 504) == ()  # already DA3's input: no resize


def test_legacy_plan_is_the_old_floor_sizing() -> None:
    assert plan_output_size((480, 640), legacy_area_floor_plan((480, 640), 224)) == (182, 252)
    assert legacy_area_floor_plan((182, 252), 224) == ()


def test_lookup_is_by_family_and_by_recorded_name() -> None:
    assert for_family("pi3").name == "pi3-kvtracker-v1"
    assert for_family("da3").name == "da3-upper-bound-v1"
    assert for_family("da3").default_resolution == 504 and for_family("pi3").default_resolution == 308
    assert set(FAMILY_PREPROCESSING.values()) <= set(PREPROCESSINGS)
    assert named(LEGACY_PREPROCESSING) is LEGACY_AREA_FLOOR  # the name old maps stand for
    with pytest.raises(ConfigError, match="no preprocessing"):
        for_family("vggt")
    with pytest.raises(ConfigError, match="unknown preprocessing"):
        named("pi3-kvtracker-v9")

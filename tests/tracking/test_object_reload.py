"""Object mode on a desk, from one box, and found again from the saved map with no box at all.

A short version of ``benchmarks/object_desk.py`` (same measures, 150 frames instead of 720; the
full runs and the reload in a new process are the slow tests of
``tests/benchmarks/test_object_desk.py``): a 12 x 9 x 16 cm box on a desk beside another, the
walk around it at 0.5 m, the true box on frame 0 only; then the map loaded by a new tracker,
whose second walk starts looking 60 degrees away and pans onto the object.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from benchmarks.object_desk import SIZE, Layout, first_walk, layout, second_walk
from kvtracker_sdk.tracking.facade.tracker import Tracker
from kvtracker_sdk.types import RegionSource, StateReason, TrackingState

FRAMES = 150


@pytest.fixture(scope="module")
def desk() -> Layout:
    return layout("desk", FRAMES)


@pytest.fixture(scope="module")
def saved(desk: Layout, tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    path = tmp_path_factory.mktemp("object_map") / "mug.kvmap"
    return first_walk(desk, path), path


def test_the_object_on_a_desk_is_tracked_from_one_box(saved: tuple[dict, Path]) -> None:
    figures, _ = saved
    assert figures["tracked"] >= 0.9 * figures["frames"]
    assert figures["iou_ok"] >= 0.95  # the target; measured: 100 % (720 frames: 98 %)
    assert figures["frame0_box_iou_ok"] < 0.5  # holding the tap's box would not do
    assert figures["within_1cm"] >= 0.9  # measured: 100 % (was 28 % before the separation)
    assert figures["origin_error_of_radius"] <= 0.1
    assert max(figures["extent_error_per_axis"]) <= 0.15
    assert figures["has_up"] and figures["up_error_deg"] < 2.0


def test_a_loaded_object_map_finds_the_object_with_no_box(
    desk: Layout, saved: tuple[dict, Path]
) -> None:
    figures = second_walk(desk, saved[1], frames=80)
    assert figures["mode"] == "object"  # from the map: nobody said --mode object
    assert figures["sources_before"] == []  # no region at all while searching
    assert 0 <= figures["frames_to_find"] <= 10  # measured: 2 (recover_after = 3)
    assert figures["iou_ok"] >= 0.95


def test_an_object_not_in_view_says_a_box_is_needed(desk: Layout, saved: tuple[dict, Path]) -> None:
    backend = desk.backend()
    frames = list(backend.frames(SIZE, textured=False, start=FRAMES, stop=FRAMES + 45))
    with Tracker.from_map(saved[1], backend, {"object": {"search_frames": 8}}) as tracker:
        states = []
        tracker.events.on_state_change(states.append)
        results = [tracker.push_frame(f.image, timestamp=f.timestamp) for f in frames[:20]]
        # the camera looks away for ~29 frames: not found after 8, and the reason says so
        assert [r.reason for r in results[6:8]] == [StateReason.MAP_LOADED,
                                                    StateReason.OBJECT_NOT_FOUND]
        assert all(r.state is TrackingState.RELOCALIZING and r.region is None for r in results)
        assert any(e.reason is StateReason.OBJECT_NOT_FOUND for e in states)
        # it keeps looking: once the object comes into view it is found
        results += [tracker.push_frame(f.image, timestamp=f.timestamp) for f in frames[20:]]
        assert results[-1].reason is StateReason.RELOCALIZED and results[-1].pose_valid
        assert results[-1].region is not None
        assert results[-1].region.source is RegionSource.PREDICTED
        assert tracker.keyframe_map is not None
        # searching frames never became keyframes
        assert all(kf.frame_index < FRAMES for kf in tracker.keyframe_map.keyframes)
    assert np.isfinite(results[-1].T_cam_object).all()

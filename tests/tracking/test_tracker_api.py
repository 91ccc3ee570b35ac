"""The tracker's public surface: at most 25 members, the grouped views (``events``, ``live``,
``object``, ``world``, ``export``, the ``camera`` property), and the old names, which still work
for one release and warn with their new spelling."""

from __future__ import annotations

import re
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.cli.demo_trajectory import handheld_orbit
from kvtracker_sdk.errors import InputError, StateError
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.tracking.core.events import EventKind, Subscription
from kvtracker_sdk.tracking.facade.tracker import Tracker
from kvtracker_sdk.tracking.facade.tracker_renames import RENAMED
from kvtracker_sdk.tracking.live.live_intake import LiveStats
from kvtracker_sdk.world import ScaleSource
from tests.tracking.sim_session import SIZE, WAIT_S, drive, make_tracker

PUBLIC_MEMBERS = [
    "backend", "camera", "close", "config", "events", "export", "from_map", "from_pretrained",
    "get_pose", "get_tracked_pose", "initialize", "keyframe_map", "live", "map_status", "object",
    "push_frame", "reason", "reset", "save_map", "set_backend", "snapshot", "state", "submit",
    "wait_for_map", "world",
]


def test_the_tracker_has_at_most_25_public_members() -> None:
    members = sorted(name for name in dir(Tracker) if not name.startswith("_"))
    assert members == PUBLIC_MEMBERS
    assert len(members) <= 25
    assert not set(RENAMED) & set(members)  # the old names are no members


@pytest.fixture(scope="module")
def scene() -> Iterator[Tracker]:
    """A scene-mode tracker with a one-keyframe map."""
    backend = SimulatedBackend(orbit(600, turns=0.5), seed=4)
    with make_tracker(backend) as tracker:
        drive(tracker, backend, stop=1)
        yield tracker


@pytest.fixture(scope="module")
def object_mode() -> Iterator[Tracker]:
    """An object-mode tracker given the sphere's box on its first frame, after two frames."""
    backend = SimulatedBackend(handheld_orbit(60, seed=3), seed=2)
    with make_tracker(backend, mode="object") as tracker:
        for frame in backend.frames(SIZE, textured=False, stop=2):
            bbox = backend.scene.object_box(frame.T_world_cam, SIZE) if frame.index == 0 else None
            tracker.push_frame(frame.image, timestamp=frame.timestamp, bbox=bbox)
        yield tracker


def _registers(name: str) -> Callable[[Tracker, Any, Path], None]:
    def check(tracker: Tracker, old: Any, _tmp: Path) -> None:
        handle = old(print)
        assert isinstance(handle, Subscription) and handle.kind is EventKind(name)
        assert tracker.events.unregister(handle)  # it was registered on the tracker's bus

    return check


def _unregisters(tracker: Tracker, old: Any, _tmp: Path) -> None:
    handle = tracker.events.on_keyframe(print)
    assert old(handle) is True and old(handle) is False


def _latest(tracker: Tracker, old: Any, _tmp: Path) -> None:
    assert old() is None and tracker.live.latest() is None  # nothing submitted to this tracker


def _stats(tracker: Tracker, old: Any, _tmp: Path) -> None:
    assert old == tracker.live.stats == LiveStats.empty()


def _wait_idle(tracker: Tracker, old: Any, _tmp: Path) -> None:
    assert old(0.0) is True


def _object_frame(tracker: Tracker, old: Any, _tmp: Path) -> None:
    new = tracker.object.frame
    assert old is not None and new is not None
    np.testing.assert_array_equal(old.T_world_object, new.T_world_object)


def _object_region(tracker: Tracker, old: Any, _tmp: Path) -> None:
    assert old is not None and old == tracker.object.region


def _set_segmenter(tracker: Tracker, old: Any, _tmp: Path) -> None:
    old(None)
    with pytest.raises(InputError, match="segmenter"):
        old("not a segmenter")


def _set_known_distance(tracker: Tracker, old: Any, _tmp: Path) -> None:
    old(2.0, [0, 0, 0], [1, 0, 0])
    assert tracker.map_status.world.scale_source is ScaleSource.KNOWN_SIZE


def _set_object_height(tracker: Tracker, old: Any, _tmp: Path) -> None:
    old(0.5)  # object mode: accepted (applied once the map holds object points)
    with pytest.raises(InputError):
        old(-1.0)


def _export_point_cloud(tracker: Tracker, old: Any, tmp: Path) -> None:
    assert old(tmp / "cloud.ply") > 0 and (tmp / "cloud.ply").stat().st_size > 0


def _export_trajectory(tracker: Tracker, old: Any, tmp: Path) -> None:
    assert old(tmp / "keyframes.txt") == 1


def _set_camera(tracker: Tracker, old: Any, _tmp: Path) -> None:
    camera = Camera(200.0, 200.0, 126.0, 98.0, 252, 196)
    old(camera)
    assert tracker.camera is camera
    with pytest.raises(InputError, match="camera"):
        old(42)
    old(camera=None)
    assert tracker.camera is None


# old name -> (the tracker it is checked on, a check that it still does what it did)
CHECKS: dict[str, tuple[str, Callable[[Tracker, Any, Path], None]]] = {
    **{kind.value: ("scene", _registers(kind.value)) for kind in EventKind},
    "unregister": ("scene", _unregisters),
    "latest": ("scene", _latest),
    "stats": ("scene", _stats),
    "wait_idle": ("scene", _wait_idle),
    "object_frame": ("object_mode", _object_frame),
    "object_region": ("object_mode", _object_region),
    "set_segmenter": ("object_mode", _set_segmenter),
    "set_known_distance": ("scene", _set_known_distance),
    "set_object_height": ("object_mode", _set_object_height),
    "export_point_cloud": ("scene", _export_point_cloud),
    "export_trajectory": ("scene", _export_trajectory),
    "set_camera": ("scene", _set_camera),
}


def test_every_old_name_still_works_and_warns_with_its_new_spelling(
    request: pytest.FixtureRequest, tmp_path: Path,
) -> None:
    assert set(CHECKS) == set(RENAMED)  # a rename without a check fails here
    for name, (fixture, check) in CHECKS.items():
        tracker = request.getfixturevalue(fixture)
        with pytest.warns(DeprecationWarning, match=re.escape(f"use tracker.{RENAMED[name]}")):
            old = getattr(tracker, name)
        check(tracker, old, tmp_path)


def test_an_unknown_name_raises_attribute_error_without_a_warning(scene: Tracker) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any warning would raise here
        with pytest.raises(AttributeError, match="on_keyframes"):
            scene.on_keyframes  # type: ignore[attr-defined]  # noqa: B018
    assert not hasattr(scene, "_not_a_member")


def test_camera_is_assigned_with_the_old_validation(scene: Tracker) -> None:
    camera = Camera(200.0, 200.0, 126.0, 98.0, 252, 196)
    scene.camera = camera
    with pytest.raises(InputError, match="camera must be"):
        scene.camera = "pinhole"  # type: ignore[assignment]
    assert scene.camera is camera  # a refused value changes nothing
    scene.camera = None
    assert scene.camera is None


def test_a_live_view_taken_before_the_first_submit_sees_the_intake() -> None:
    backend = SimulatedBackend(orbit(600, turns=0.5), seed=4)
    with make_tracker(backend) as tracker:
        live = tracker.live
        assert live.latest() is None and live.stats == LiveStats.empty() and live.wait_idle(0.0)
        frame = next(iter(backend.frames(SIZE, stop=1, textured=False)))
        tracker.submit(frame.image, timestamp=frame.timestamp)
        assert live.wait_idle(WAIT_S)
        assert live.stats.processed == 1 and live.latest() is not None


def test_set_object_height_keeps_its_object_mode_check(scene: Tracker) -> None:
    with pytest.raises(StateError, match="object mode"):
        scene.world.set_object_height(0.5)

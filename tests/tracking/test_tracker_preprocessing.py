"""Maps remember which preprocessing made their frames; old maps track, and are not extended
across preprocessings unless asked."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.errors import MapPreprocessingError
from kvtracker_sdk.io.map_file.map_file import load_map, read_map_info
from kvtracker_sdk.preprocess import LEGACY_AREA_FLOOR
from kvtracker_sdk.tracking.core import model_input
from kvtracker_sdk.tracking.facade.tracker import Tracker
from kvtracker_sdk.tracking.mapping.map_keeper import MapKeeper
from kvtracker_sdk.types import TrackingState
from tests.io.map_factory import rewrite_header
from tests.tracking.sim_session import make_tracker

OLD_SIZE = (182, 252)  # the legacy model input of 4:3 frames at d = 224: rendered, no resize
INTERVAL = {"keyframing": {"interval_frames": 10}, "relocalization": {"recover_after": 2}}


def _backend() -> SimulatedBackend:
    return SimulatedBackend(orbit(num_frames=200, turns=0.25), seed=5, pass_jitter=0.0)


def _push(tracker: Tracker, backend: SimulatedBackend, start: int, stop: int) -> list:
    return [
        tracker.push_frame(f.image, timestamp=f.timestamp)
        for f in backend.frames(OLD_SIZE, start=start, stop=stop, textured=False)
    ]


@pytest.fixture(scope="module")
def old_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A map as saved by earlier SDKs: frames prepared the legacy way, no header field."""
    path = tmp_path_factory.mktemp("legacy") / "old.kvmap"
    backend = _backend()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(model_input, "for_family", lambda family: LEGACY_AREA_FLOOR)
        with make_tracker(backend, **INTERVAL) as tracker:
            _push(tracker, backend, 0, 21)
            tracker.save_map(path)
    metadata_keys = rewrite_header(path.read_bytes(), lambda h: h["__metadata__"].pop("preprocessing"))
    path.write_bytes(metadata_keys)
    return path


def test_a_map_without_the_field_loads_as_legacy(old_map: Path) -> None:
    info = read_map_info(old_map)
    assert info.preprocessing == "legacy-area-floor" and info.resolution == OLD_SIZE
    assert load_map(old_map).keyframe_map.preprocessing == "legacy-area-floor"


def test_new_maps_record_their_preprocessing(tmp_path: Path) -> None:
    backend = _backend()
    with make_tracker(backend, **INTERVAL) as tracker:
        for f in backend.frames((196, 252), stop=3, textured=False):
            tracker.push_frame(f.image, timestamp=f.timestamp)
        info = tracker.save_map(tmp_path / "new.kvmap")
    assert info.preprocessing == read_map_info(tmp_path / "new.kvmap").preprocessing
    assert info.preprocessing == "pi3-kvtracker-v1" and info.resolution == (196, 252)


def test_an_old_map_tracks_but_is_not_extended(old_map: Path) -> None:
    backend = _backend()
    with Tracker.from_map(old_map, backend) as tracker:
        before = tracker.keyframe_map
        results = _push(tracker, backend, 21, 61)  # 4 keyframe intervals
        assert tracker.keyframe_map is before  # no keyframe added, no rebuild
    assert results[-1].state is TrackingState.TRACKING and results[-1].pose_valid
    assert not any(r.is_keyframe for r in results)


def test_extending_across_preprocessings_is_a_typed_error(old_map: Path) -> None:
    backend = _backend()
    with Tracker.from_map(old_map, backend) as tracker:
        frame = tracker._preparer.prepare(  # what push_frame prepares for this map
            next(iter(backend.frames(OLD_SIZE, start=30, stop=31, textured=False))).image,
            map_resolution=OLD_SIZE, map_preprocessing="legacy-area-floor",
        )
        kf_map, config = tracker.keyframe_map, tracker.config
    assert kf_map is not None
    keeper = MapKeeper(config, preprocessing="pi3-kvtracker-v1")
    keeper.load(kf_map)
    assert not keeper.extendable and not keeper.wants_keyframe(np.eye(4), 10_000)
    with pytest.raises(MapPreprocessingError, match="rebuild=True"):
        keeper.propose(backend, frame, 30, np.eye(4))
    keeper.close()


def test_rebuild_extends_an_old_map_in_its_own_preprocessing(old_map: Path, tmp_path: Path) -> None:
    backend = _backend()
    with Tracker.from_map(old_map, backend, rebuild=True) as tracker:
        kept = tracker.keyframe_map.num_keyframes  # type: ignore[union-attr]
        results = _push(tracker, backend, 21, 61)
        info = tracker.save_map(tmp_path / "extended.kvmap")
    assert any(r.is_keyframe for r in results) and info.num_keyframes > kept
    assert info.preprocessing == "legacy-area-floor" and info.resolution == OLD_SIZE

"""A backend defined outside the package, with its own family, runs a whole session, saves its
map and reloads it: through a registered family, or through the preprocessing it declares."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kvtracker_sdk import Backend, Tracker, TrackerConfig, TrackingState
from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.io.map_file.map_file import read_map_info
from kvtracker_sdk.preprocess import DA3_UPPER_BOUND, FAMILY_PREPROCESSING, register_family
from tests.tracking.app_backend import ACME_PREPROCESSING, AcmeBackend
from tests.tracking.sim_session import SIZE

FRAMES = 40


def _network() -> SimulatedBackend:
    return SimulatedBackend(orbit(FRAMES, turns=0.25), seed=11)


def _session_then_reload(backend: AcmeBackend, folder: Path) -> tuple[list[bool], Path]:
    """Track the orbit, save the map, then relocalise a new tracker against the saved map."""
    config = TrackerConfig(resolution=224, keyframing={"interval_frames": 10})
    frames = list(_network().frames(SIZE, textured=False))
    with Tracker(config, backend) as tracker:
        results = [tracker.push_frame(f.image, timestamp=f.timestamp) for f in frames]
        assert tracker.map_status.num_keyframes >= 3
        path = folder / "acme.kvmap"
        tracker.save_map(path)
    assert sum(r.pose_valid for r in results) >= FRAMES - 2  # bootstrap frames have no pose
    with Tracker.from_map(path, backend) as reloaded:
        assert reloaded.state is TrackingState.RELOCALIZING
        again = [reloaded.push_frame(f.image, timestamp=f.timestamp) for f in frames[::7]]
        assert reloaded.state is TrackingState.TRACKING
        # the reloaded map answers in the saved world frame: the same frame, the same pose
        for result, frame in zip(again, frames[::7], strict=True):
            first = results[frame.index]
            if result.pose_valid and first.pose_valid:
                assert result.pose is not None and first.pose is not None
                np.testing.assert_allclose(result.pose.translation, first.pose.translation,
                                           atol=0.05)  # tracking noise of 1 cm per axis
    assert not backend.closed  # a tracker never closes a backend it was given
    return [r.pose_valid for r in again], path


def test_a_registered_family_runs_a_session_saves_and_reloads(tmp_path: Path) -> None:
    backend = AcmeBackend(_network(), family="acme-registered")
    assert isinstance(backend, Backend)  # the runtime-checkable protocol holds
    register_family("acme-registered", "pi3-kvtracker-v1")
    register_family("acme-registered", "pi3-kvtracker-v1")  # again: a no-op
    assert FAMILY_PREPROCESSING["acme-registered"] == "pi3-kvtracker-v1"
    valid, path = _session_then_reload(backend, tmp_path)
    assert any(valid)
    info = read_map_info(path)
    assert info.backend.family == "acme-registered" and info.preprocessing == "pi3-kvtracker-v1"


def test_a_declared_preprocessing_needs_no_registration(tmp_path: Path) -> None:
    backend = AcmeBackend(_network(), family="acme-declared", declare_preprocessing=True)
    assert "acme-declared" not in FAMILY_PREPROCESSING
    valid, path = _session_then_reload(backend, tmp_path)
    assert any(valid)
    assert read_map_info(path).preprocessing == ACME_PREPROCESSING.name


def test_an_unknown_family_is_refused_saying_how_to_add_it() -> None:
    with pytest.raises(ConfigError, match="register_family"):
        Tracker(TrackerConfig(), AcmeBackend(_network(), family="acme-unknown"))


def test_registration_refuses_to_redefine_a_family_or_a_name() -> None:
    with pytest.raises(ConfigError, match="already registered"):
        register_family("pi3", DA3_UPPER_BOUND)
    register_family("acme-once", "pi3-kvtracker-v1")
    with pytest.raises(ConfigError, match="already registered"):
        register_family("acme-once", "da3-upper-bound-v1")
    with pytest.raises(ConfigError, match="taken by another"):
        register_family("acme-other", ACME_PREPROCESSING.__class__(
            "pi3-kvtracker-v1", 224, ACME_PREPROCESSING.plan,
            ACME_PREPROCESSING.single_step_filter, ACME_PREPROCESSING.mask_resampling))
    with pytest.raises(ConfigError, match="unknown preprocessing"):
        register_family("acme-other", "no-such-pipeline")

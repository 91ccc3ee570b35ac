"""Intrinsics in map files: a bit-exact round trip, ``map info``, and a warning when a session's
given camera differs from the saved one."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.geometry.camera import Camera, IntrinsicsSource
from kvtracker_sdk.io.map_file.map_file import read_map_info
from kvtracker_sdk.tracking.facade.tracker import Tracker
from tests.cli.invoke import invoke

SIZE = (240, 320)
# values whose decimal forms are long: a lossy encoding (e.g. "%.6g") would change them
GIVEN = Camera(259.123456789012345, 258.98765432109876, 159.5000000001, 119.49999999, 320, 240,
               (0.01234567890123, -0.0009876543210, 1e-17, 0.0, 3.3333333333333335e-05))


@pytest.fixture(scope="module")
def backend() -> SimulatedBackend:
    return SimulatedBackend(orbit(12), camera_size=SIZE, seed=2)


def _save(backend: SimulatedBackend, path: Path, camera: Camera | None) -> None:
    with Tracker(TrackerConfig(), backend, camera=camera) as tracker:
        for frame in backend.frames(SIZE, stop=3):
            tracker.push_frame(frame.image, timestamp=frame.timestamp)
        tracker.save_map(path)


def test_given_intrinsics_round_trip_bit_exact_and_show_in_map_info(
    backend: SimulatedBackend, tmp_path: Path
) -> None:
    path = tmp_path / "given.kvmap"
    _save(backend, path, GIVEN)
    info = read_map_info(path)
    assert info.camera == GIVEN  # dataclass equality: every float and coefficient bit for bit
    assert info.camera is not None and info.camera.distortion == GIVEN.distortion
    assert info.camera_source is IntrinsicsSource.GIVEN

    facts = json.loads(invoke("map", "info", path, "--json").stdout)
    assert facts["camera"]["fx"] == GIVEN.fx and facts["camera"]["source"] == "given"
    text = invoke("map", "info", path).stdout
    assert "camera     fx 259.123 fy 258.988 cx 159.5 cy 119.5 at 320x240 px (given)" in text


def test_estimated_intrinsics_are_saved_with_their_source(
    backend: SimulatedBackend, tmp_path: Path
) -> None:
    path = tmp_path / "estimated.kvmap"
    _save(backend, path, None)
    info = read_map_info(path)
    assert info.camera_source is IntrinsicsSource.ESTIMATED and info.camera is not None
    assert info.camera.fx == pytest.approx(0.81 * 320, rel=0.01)


def test_loading_with_other_intrinsics_warns(
    backend: SimulatedBackend, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "given.kvmap"
    _save(backend, path, GIVEN)
    with caplog.at_level(logging.WARNING, logger="kvtracker_sdk"):
        Tracker.from_map(path, backend, camera=GIVEN).close()  # the same camera: silent
        assert not [r for r in caplog.records if r.getMessage() == "map_camera_mismatch"]
        other = Camera(300.0, 300.0, 159.5, 119.5, 320, 240)
        with Tracker.from_map(path, backend, camera=other) as tracker:
            assert tracker.camera == other  # not refused: the session uses its own camera
    warnings = [r for r in caplog.records if r.getMessage() == "map_camera_mismatch"]
    assert len(warnings) == 1 and warnings[0].levelno == logging.WARNING

"""One answer to "can this map run here?": typed reasons, in the order loads report them."""

from __future__ import annotations

from pathlib import Path

import pytest

from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.errors import ConfigError, MapModelMismatchError
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.io.map_file.compatibility import (
    MismatchKind,
    TrackerRequest,
    map_compatibility,
)
from kvtracker_sdk.io.map_file.map_file import load_map, read_map_info, save_map
from kvtracker_sdk.io.map_file.map_format import MapInfo
from tests.io.map_factory import TRACKER_CONFIG, backend_info, make_map


@pytest.fixture(scope="module")
def info(tmp_path_factory: pytest.TempPathFactory) -> MapInfo:
    path = tmp_path_factory.mktemp("compat") / "m.kvmap"
    save_map(path, make_map(), backend_info=backend_info(), tracker_config_json=TRACKER_CONFIG,
             mode="object", camera=Camera(30.0, 30.0, 20.5, 13.5, 42, 28))  # fmt: skip
    return read_map_info(path)


def test_a_map_that_fits_runs_under_its_saved_config(info: MapInfo) -> None:
    answer = map_compatibility(info, backend_info(), tracker=TrackerRequest())
    assert answer.ok and answer.mismatches == () and answer.camera_agrees
    assert answer.config is not None and answer.config.mode.value == "object"
    assert answer.config.keyframing.view_angle_deg == 10.0  # the saved config, not the default


def test_every_reason_is_reported_typed_and_the_first_is_raised(info: MapInfo) -> None:
    other_model = backend_info(weights_fingerprint="another-weights")
    answer = map_compatibility(
        info, other_model, tracker=TrackerRequest(TrackerConfig(mode="scene")), source="m"
    )
    assert not answer.ok and answer.config is None
    assert [m.kind for m in answer.mismatches] == [MismatchKind.MODEL, MismatchKind.MODE]
    assert [m.error for m in answer.mismatches] == [MapModelMismatchError, ConfigError]
    with pytest.raises(MapModelMismatchError, match="weights fingerprint"):
        answer.raise_if_refused()
    mode_only = map_compatibility(info, backend_info(), tracker=TrackerRequest({"mode": "scene"}))
    with pytest.raises(ConfigError, match="saved in object mode"):
        mode_only.raise_if_refused()


def test_another_camera_is_reported_not_refused(info: MapInfo) -> None:
    other = TrackerRequest(camera=Camera(45.0, 45.0, 20.5, 13.5, 42, 28))
    answer = map_compatibility(info, backend_info(), tracker=other)
    assert answer.ok and not answer.camera_agrees


def test_load_map_asks_it_before_reading_tensors(tmp_path: Path, info: MapInfo) -> None:
    path = tmp_path / "m.kvmap"
    save_map(path, make_map(), backend_info=backend_info(), tracker_config_json=TRACKER_CONFIG,
             mode="object")  # fmt: skip
    loaded = load_map(path, expected_backend=backend_info(), tracker=TrackerRequest())
    assert loaded.compatibility is not None and loaded.compatibility.ok
    data = bytearray(path.read_bytes())
    data[-64:] = bytes(64)  # corrupt tensor bytes: a refusal from the header comes first
    path.write_bytes(bytes(data))
    with pytest.raises(MapModelMismatchError):
        load_map(path, expected_backend=backend_info(family="da3"))

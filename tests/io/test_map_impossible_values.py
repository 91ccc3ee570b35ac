"""Maps whose numbers cannot be right are refused at load; a pose that is not finite is never
valid; a map path may be a symbolic link, and must be a path.

Version-2/3 (quantised) maps used to load with quantisation scales of 0, negative, subnormal or
NaN (poses marked valid but off by up to 79 m), and with a gauge scale of 1e308 (frames
TRACKING with ``pose_valid=True`` and a translation of -inf): every file here has its checksums
recomputed, as anyone editing a file can.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from kvtracker_sdk.errors import MapError, MapIOError, TrackingFailedError
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.io.map_file.map_file import load_map
from tests.io.impossible_maps import base_files, impossible_maps
from tests.io.map_factory import rewrite_header
from tests.tracking.sim_session import SIZE, make_tracker

DEFAULT_CASES = 200  # seeded; benchmarks/fuzz_inputs.py runs more, each in a fresh process


@pytest.fixture(scope="module")
def bases(tmp_path_factory: pytest.TempPathFactory) -> dict[tuple[str, bool], bytes]:
    return base_files(tmp_path_factory.mktemp("quantised"))


def test_every_map_with_an_impossible_number_is_refused(
    bases: dict[tuple[str, bool], bytes], tmp_path: Path
) -> None:
    path = tmp_path / "case.kvmap"
    for data in bases.values():  # the unedited files load
        path.write_bytes(data)
        load_map(path)
    loaded = []
    for name, data in impossible_maps(bases, DEFAULT_CASES, seed=34):
        path.write_bytes(data)
        try:
            load_map(path)
            loaded.append(name)
        except MapError:
            pass
    assert loaded == []


@pytest.mark.parametrize("byte", [0x00, 0x84, 0x01, 0x7E], ids=["zero", "negative", "subnormal", "nan"])
def test_a_zero_negative_subnormal_or_nan_kv_scale_is_refused_naming_the_scale(
    bases: dict[tuple[str, bool], bytes], tmp_path: Path, byte: int
) -> None:
    from tests.io.impossible_maps import _reseal, split_file

    header, body = split_file(bases[("int8", True)])
    start, _ = header["layers.2.value_scale"]["data_offsets"]
    edited = bytearray(body)
    edited[start + 5] = byte
    path = tmp_path / "scaled.kvmap"
    path.write_bytes(_reseal(header, edited, ["layers.2.value_scale"]))
    with pytest.raises(MapError, match="layer 2 value_scale"):
        load_map(path)


@pytest.mark.parametrize("scale", [1e308, 1e7, 1e-7])
def test_an_impossible_gauge_scale_is_refused(
    bases: dict[tuple[str, bool], bytes], tmp_path: Path, scale: float
) -> None:
    def edit(header: dict) -> None:
        gauge = json.loads(header["__metadata__"]["gauge"])
        gauge["scale"] = scale
        header["__metadata__"]["gauge"] = json.dumps(gauge)

    path = tmp_path / "gauge.kvmap"
    path.write_bytes(rewrite_header(bases[("float8_e4m3fn", False)], edit))
    with pytest.raises(MapError, match="gauge scale"):
        load_map(path)


def test_a_symlink_to_a_map_loads_and_a_path_must_be_a_path(
    bases: dict[tuple[str, bool], bytes], tmp_path: Path
) -> None:
    (tmp_path / "maps").mkdir()
    (tmp_path / "maps" / "real.kvmap").write_bytes(bases[("int8", True)])
    (tmp_path / "links").mkdir()
    os.symlink("../maps/real.kvmap", tmp_path / "links" / "link.kvmap")  # relative, another folder
    assert load_map(tmp_path / "links" / "link.kvmap").info.num_keyframes == 3
    with pytest.raises(MapIOError, match="path"):
        load_map(5)  # type: ignore[arg-type]
    with pytest.raises(MapIOError, match="path"):
        load_map(None)  # type: ignore[arg-type]


def test_a_non_finite_world_pose_is_a_failed_frame_never_a_valid_one() -> None:
    """The second line behind the gauge check: a map already in memory whose gauge scale
    overflows the pose (as a file edited for an older SDK would give)."""
    from kvtracker_sdk.backends.simulated import SimulatedBackend
    from kvtracker_sdk.backends.simulated_scene import orbit

    backend = SimulatedBackend(orbit(20), translation_noise_m=0.0, rotation_noise_deg=0.0)
    frames = [(f.image, f.timestamp) for f in backend.frames(SIZE, textured=False)]
    with make_tracker(backend) as tracker:
        assert tracker.push_frame(frames[0][0], timestamp=frames[0][1]).pose_valid
        kf_map = tracker.keyframe_map
        assert kf_map is not None
        gauge = kf_map.gauge
        object.__setattr__(kf_map, "gauge", Sim3(gauge.rotation, gauge.translation + 1.0, 1e308))
        results = [tracker.push_frame(image, timestamp=stamp) for image, stamp in frames[1:6]]
    for result in results:
        assert not result.pose_valid
        assert result.pose is None or not np.all(np.isfinite(result.pose.T_world_cam))
        assert isinstance(result.error, TrackingFailedError)

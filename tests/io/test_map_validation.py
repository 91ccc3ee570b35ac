"""Loading checks what the header checksum cannot: values that are well-formed but impossible.

Each file below is tampered the way an attacker (or a buggy tool) would, with every checksum
recomputed, so only the value checks stand between it and the tracker: a gauge rotation that is
not one, keyframe poses that are not rigid, confidences outside [0, 1] or NaN, an unknown mode,
a saved tracker config whose resolution cannot give the map's keyframes, and a generation out of
range. Each is a typed map error. Saving refuses the same values: the SDK never writes a map it
would refuse to load.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from kvtracker_sdk.errors import MapCorruptedError, MapError, MapFormatError
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.io.map_file.compatibility import TrackerRequest, map_compatibility
from kvtracker_sdk.io.map_file.map_file import load_map, read_map_info, save_map
from kvtracker_sdk.io.map_file.map_schema import MAX_GENERATION
from tests.io.map_factory import (
    TRACKER_CONFIG,
    backend_info,
    join_file,
    make_map,
    rewrite_header,
    split_file,
)

DTYPES = {"F64": np.float64, "F32": np.float32}


def saved(folder: Path, *, config: str = TRACKER_CONFIG, **options: Any) -> Path:
    path = folder / "m.kvmap"
    save_map(
        path, make_map(**options), backend_info=backend_info(), tracker_config_json=config,
        mode="object",
    )  # fmt: skip
    return path


def refused_for_tracker(path: Path) -> None:
    """Raise what loading ``path`` into a tracker with its saved config raises (header only)."""
    info = read_map_info(path)
    answer = map_compatibility(info, backend_info(), tracker=TrackerRequest(), source=str(path))
    answer.raise_if_refused()


def edit_tensor(path: Path, name: str, edit: Callable[[np.ndarray], None]) -> None:
    """Apply ``edit`` to tensor ``name`` in place and recompute its checksum and the header's."""
    header, body = split_file(path.read_bytes())
    entry = header[name]
    begin, end = entry["data_offsets"]
    array = np.frombuffer(body[begin:end], dtype=DTYPES[entry["dtype"]]).reshape(entry["shape"])
    array = array.copy()
    edit(array)
    body = body[:begin] + array.tobytes() + body[end:]
    checksums = json.loads(header["__metadata__"]["tensor_sha256"])
    checksums[name] = hashlib.sha256(array.tobytes()).hexdigest()
    header["__metadata__"]["tensor_sha256"] = json.dumps(checksums, separators=(",", ":"))
    path.write_bytes(rewrite_header(join_file(header, body), lambda h: None))


def edit_metadata(path: Path, **fields: str) -> None:
    path.write_bytes(rewrite_header(path.read_bytes(), lambda h: h["__metadata__"].update(fields)))


def scaled_rotation(array: np.ndarray) -> None:
    array[1, :3, :3] *= 1.5  # keyframe 1: a scaled, no longer rigid pose


@pytest.mark.parametrize(
    ("tensor", "edit", "message"),
    [
        ("keyframes.T_world_cam", scaled_rotation, "not a finite rigid transform"),
        ("keyframes.T_world_cam", lambda a: a.__setitem__((2, 3, 0), 0.5), "rigid"),
        ("keyframes.confidence", lambda a: a.__setitem__((0, 3, 4), np.nan), "confidence map"),
        ("keyframes.confidence", lambda a: a.__setitem__((2, 0, 0), 2.0), "confidence map"),
        ("keyframes.mean_confidence", lambda a: a.__setitem__(1, -0.5), "mean confidence"),
    ],
    ids=["scaled-pose", "pose-last-row", "nan-confidence", "confidence-2", "mean-confidence"],
)
def test_impossible_keyframe_values_are_refused(
    tmp_path: Path, tensor: str, edit: Callable[[np.ndarray], None], message: str
) -> None:
    path = saved(tmp_path)
    edit_tensor(path, tensor, edit)
    with pytest.raises(MapCorruptedError, match=message):
        load_map(path)


def test_a_gauge_rotation_that_is_not_one_is_refused(tmp_path: Path) -> None:
    path = saved(tmp_path)
    gauge = json.loads(split_file(path.read_bytes())[0]["__metadata__"]["gauge"])
    gauge["rotation"] = (1.5 * np.array(gauge["rotation"])).tolist()
    edit_metadata(path, gauge=json.dumps(gauge))
    with pytest.raises(MapFormatError, match="gauge rotation is not orthonormal"):
        read_map_info(path)


def test_an_unknown_mode_is_a_map_error(tmp_path: Path) -> None:
    path = saved(tmp_path)
    edit_metadata(path, tracker_config=json.dumps({"mode": "banana"}))
    with pytest.raises(MapFormatError, match="mode must be one of"):
        read_map_info(path)


@pytest.mark.parametrize("side", [224, 518])
def test_a_saved_resolution_that_cannot_give_the_keyframes_is_refused(
    tmp_path: Path, side: int
) -> None:
    config = json.dumps({"mode": "object", "resolution": side})
    path = saved(tmp_path, config=config)  # 28x42 keyframes come from a side of 28 to 42 px
    with pytest.raises(MapFormatError, match=f"resolution {side}, which cannot give"):
        refused_for_tracker(path)


@pytest.mark.parametrize("generation", [str(MAX_GENERATION + 1), "9" * 18])
def test_a_generation_out_of_range_is_refused(tmp_path: Path, generation: str) -> None:
    path = saved(tmp_path)
    edit_metadata(path, generation=generation)
    with pytest.raises(MapFormatError, match="generation"):
        read_map_info(path)


def test_the_largest_generation_loads(tmp_path: Path) -> None:
    assert read_map_info(saved(tmp_path, generation=MAX_GENERATION)).generation == MAX_GENERATION


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"generation": MAX_GENERATION + 1}, "generation"),
        ({"gauge": Sim3(1.5 * np.eye(3), np.zeros(3))}, "gauge rotation"),
        ({"pose": 1.5}, "rigid"),
        ({"confidence": np.nan}, "confidence"),
    ],
    ids=["generation", "gauge", "pose", "confidence"],
)
def test_saving_refuses_what_loading_would(
    tmp_path: Path, change: dict[str, Any], message: str
) -> None:
    keyframe_map = make_map()
    if "generation" in change:
        keyframe_map = replace(keyframe_map, generation=change["generation"])
    if "gauge" in change:
        keyframe_map = replace(keyframe_map, gauge=change["gauge"])
    keyframes = list(keyframe_map.keyframes)
    if "pose" in change:
        pose = keyframes[1].T_world_cam.copy()
        pose[:3, :3] *= change["pose"]
        keyframes[1] = replace(keyframes[1], T_world_cam=pose)
    if "confidence" in change:
        confidence = keyframes[2].confidence_map.copy()
        confidence[0, 0] = change["confidence"]
        keyframes[2] = replace(keyframes[2], confidence_map=confidence)
    keyframe_map = replace(keyframe_map, keyframes=tuple(keyframes))
    with pytest.raises(MapError, match=message):
        save_map(
            tmp_path / "m.kvmap", keyframe_map, backend_info=backend_info(),
            tracker_config_json=TRACKER_CONFIG, mode="object",
        )  # fmt: skip
    assert list(tmp_path.iterdir()) == []

"""Saving: no stray file a cleanup cannot attribute, and names up to the filesystem's limit.

A killed save used to leave safetensors' own ``.tmpXXXXXX`` file (as large as the map) that no
cleanup matched, and target names of 238-255 bytes could not be saved at all (the temporary
name adds 18 bytes). The map is now streamed into the SDK's own temporary file.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest
import torch
from safetensors import safe_open

from kvtracker_sdk.io.files.atomic import STALE_TEMP_SECONDS
from kvtracker_sdk.io.map_file.map_file import load_map, save_map
from kvtracker_sdk.io.map_file.map_tensors import map_to_tensors
from tests.io.map_factory import TRACKER_CONFIG, backend_info, make_map, maps_equal


def save(path: Path) -> None:
    save_map(
        path, make_map(), backend_info=backend_info(), tracker_config_json=TRACKER_CONFIG,
        mode="object",
    )  # fmt: skip


def age(path: Path, seconds: float) -> None:
    then = time.time() - seconds
    os.utime(path, (then, then))


def test_stale_safetensors_temporaries_of_killed_saves_are_removed(tmp_path: Path) -> None:
    save(tmp_path / "old.kvmap")
    stale_map = tmp_path / ".tmpAb12Cd"  # a save killed inside safetensors' save_file
    fresh_map = tmp_path / ".tmpQq11Ww"  # a concurrent old-SDK save, still being written
    foreign = tmp_path / ".tmpZz99Yy"  # someone else's temporary file: not ours to remove
    for leftover in (stale_map, fresh_map):
        leftover.write_bytes((tmp_path / "old.kvmap").read_bytes())
    foreign.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{}              not a map")
    for old in (stale_map, foreign):
        age(old, 2 * STALE_TEMP_SECONDS)
    save(tmp_path / "room.kvmap")
    assert not stale_map.exists() and fresh_map.exists() and foreign.exists()


@pytest.mark.parametrize("length", [237, 238, 255])
def test_names_up_to_255_bytes_can_be_saved(tmp_path: Path, length: int) -> None:
    path = tmp_path / ("m" * (length - len(".kvmap")) + ".kvmap")
    save(path)
    save(path)  # over an existing map too (the stale-temporary scan runs on that name)
    assert maps_equal(load_map(path).keyframe_map, make_map())
    assert os.listdir(tmp_path) == [path.name]


def bits(tensor: torch.Tensor) -> torch.Tensor:
    return tensor.contiguous().reshape(-1).view(torch.uint8)  # NaN stamps compare bit for bit


def test_saved_files_read_back_with_safetensors_itself(tmp_path: Path) -> None:
    path = tmp_path / "m.kvmap"
    keyframe_map = make_map(dtype=torch.bfloat16)
    save_map(
        path, keyframe_map, backend_info=backend_info(dtype="bfloat16"),
        tracker_config_json=TRACKER_CONFIG, mode="object",
    )  # fmt: skip
    expected, _, _ = map_to_tensors(keyframe_map, keyframe_map.resolution)
    with safe_open(str(path), framework="pt") as reader:
        assert sorted(reader.keys()) == sorted(expected)
        for name, tensor in expected.items():
            read = reader.get_tensor(name)
            assert read.dtype == tensor.dtype and torch.equal(bits(read), bits(tensor)), name
        assert reader.metadata()["format"] == "kvtracker-map"

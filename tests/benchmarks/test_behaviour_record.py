"""``benchmarks/behaviour/record.py``'s comparison on the committed reference: a recording equals
itself, and a changed pose, state, map tensor or header field is caught, except the header fields
of its allow-list (recording itself is not run here: it takes the
CPU-seconds its environment.json names)."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from benchmarks.behaviour.record import REFERENCE, compare


@pytest.fixture
def copy(tmp_path: Path) -> Path:
    out = tmp_path / "copy"
    shutil.copytree(REFERENCE, out)
    return out


def _edit_map(folder: Path, run: str, edit: Callable[[dict[str, Any]], object]) -> None:
    path = folder / f"{run}.json"
    summary = json.loads(path.read_text())
    edit(summary["map"])
    path.write_text(json.dumps(summary))


def test_a_recording_equals_itself(copy: Path) -> None:
    assert compare(REFERENCE, copy) == 0


def test_one_pose_value_changed_by_one_ulp_is_caught(copy: Path) -> None:
    with np.load(copy / "scene_sync.npz") as data:
        arrays = {key: data[key] for key in data.files}
    arrays["poses"][100, 0, 3] = np.nextafter(arrays["poses"][100, 0, 3], np.inf)
    np.savez_compressed(copy / "scene_sync.npz", **arrays)
    assert compare(REFERENCE, copy) == 1


def test_a_changed_reason_is_caught(copy: Path) -> None:
    path = copy / "object_desk.json"
    summary = json.loads(path.read_text())
    summary["frames"][5]["reason"] = "RELOCALIZED"
    path.write_text(json.dumps(summary))
    assert compare(REFERENCE, copy) == 1


def test_map_differences_outside_the_allow_list_are_caught(copy: Path) -> None:
    def tensor(m: dict[str, Any]) -> None:
        m["tensors"]["layers.0.key"]["sha256"] = "0" * 64

    def new_field(m: dict[str, Any]) -> None:
        m["fields"]["something_new"] = 1

    def image(m: dict[str, Any]) -> None:
        m["keyframe_images"][1]["image"][2] = "0" * 64

    for run, edit in [("pi3_tum", tensor), ("da3_tum", new_field), ("pi3_tum_int8", image)]:
        changed = copy.parent / f"changed-{run}"
        shutil.copytree(copy, changed)
        _edit_map(changed, run, edit)
        assert compare(REFERENCE, changed) == 1, run


def test_the_allow_list_format_version_config_encoding_and_stored_images(copy: Path) -> None:
    def new_format(m: dict[str, Any]) -> None:
        m["fields"]["format_version"] = 99
        m["fields"]["tracker_config"] = {"structured": True}
        m["fields"]["keyframe_encoding"] = "png"
        m["fields"]["tensor_sha256.keyframes.image"] = "1" * 64
        m["tensors"]["keyframes.image"] = {"dtype": "U8", "shape": [123], "sha256": "2" * 64}

    _edit_map(copy, "pi3_tum_int8", new_format)
    assert compare(REFERENCE, copy) == 0


def test_a_new_config_option_is_allowed_a_changed_one_is_not(copy: Path) -> None:
    _edit_map(copy, "scene_sync", lambda m: m["loaded_config"]["relocalization"].update(new=1))
    assert compare(REFERENCE, copy) == 0
    _edit_map(copy, "scene_sync", lambda m: m["loaded_config"].update(resolution=224))
    assert compare(REFERENCE, copy) == 1

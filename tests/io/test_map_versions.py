"""Every older format version still loads: files written by the writer of versions 1-3 (kept in
``tests/data/maps``, see its README) against today's reader, and today's version 4."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from kvtracker_sdk.errors import MapFormatError
from kvtracker_sdk.io.map_file.map_file import load_map, read_map_info, save_map
from kvtracker_sdk.io.map_file.map_schema import FORMAT_VERSION
from tests.io.map_factory import (
    TRACKER_CONFIG,
    backend_info,
    compact_maps_match,
    make_map,
    maps_equal,
    rewrite_header,
    split_file,
)

OLD_MAPS = Path(__file__).parents[1] / "data" / "maps"
# how tests/data/maps was made (its README)
SMALL = {"num_keyframes": 2, "layers": 1, "heads": 1, "head_dim": 4, "size": (14, 14), "seed": 27}
OLD = {  # file -> (format version, cache storage, compact keyframe payload)
    "v1-dense-float32.kvmap": (1, None, False),
    "v2-int8-full.kvmap": (2, "int8", False),
    "v3-int8-compact.kvmap": (3, "int8", True),
}


@pytest.mark.parametrize("name", sorted(OLD))
def test_a_map_written_by_an_older_writer_loads_unchanged(name: str) -> None:
    version, storage, compact = OLD[name]
    path = OLD_MAPS / name
    assert "mode" in split_file(path.read_bytes())[0]["__metadata__"]  # the old header layout
    loaded = load_map(path, expected_backend=backend_info(layers=1, heads=1, head_dim=4))
    info = loaded.info
    assert info.format_version == version and info.dtype == (storage or "float32")
    assert info.mode == "object" and info.tracker_config == json.loads(TRACKER_CONFIG)
    assert info.image_codec == "raw" and info.keyframe_encoding == ("compact-xyz" if compact else "full")
    expected = make_map(storage=storage, **SMALL)
    same = compact_maps_match if compact else maps_equal
    assert same(loaded.keyframe_map, expected)


def test_older_version_numbers_relabelled_still_load(tmp_path: Path) -> None:
    """The version-1 file read as each version up to 3 (what version 1 holds, they hold)."""
    data = (OLD_MAPS / "v1-dense-float32.kvmap").read_bytes()
    for version in range(1, FORMAT_VERSION):
        path = tmp_path / f"v{version}.kvmap"
        path.write_bytes(rewrite_header(
            data, lambda h, v=version: h["__metadata__"].update(format_version=str(v))
        ))  # fmt: skip
        loaded = load_map(path)
        assert loaded.info.format_version == version
        assert maps_equal(loaded.keyframe_map, make_map(**SMALL))


def test_an_old_quantised_map_relabelled_version_1_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "v1.kvmap"
    path.write_bytes(rewrite_header((OLD_MAPS / "v3-int8-compact.kvmap").read_bytes(),
                                    lambda h: h["__metadata__"].update(format_version="1")))  # fmt: skip
    with pytest.raises(MapFormatError, match="needs format version >= 2"):
        read_map_info(path)


def test_an_old_header_whose_mode_contradicts_its_config_is_refused_for_a_tracker(
    tmp_path: Path,
) -> None:
    from kvtracker_sdk.io.map_file.compatibility import TrackerRequest, map_compatibility

    path = tmp_path / "scene.kvmap"  # versions 1-3 stored the mode twice: they may disagree
    path.write_bytes(rewrite_header((OLD_MAPS / "v1-dense-float32.kvmap").read_bytes(),
                                    lambda h: h["__metadata__"].update(mode="scene")))  # fmt: skip
    info = read_map_info(path)
    answer = map_compatibility(info, info.backend, tracker=TrackerRequest(), source=str(path))
    with pytest.raises(MapFormatError, match="header says scene mode"):
        answer.raise_if_refused()


def test_version_4_stores_the_mode_once_in_the_config(tmp_path: Path) -> None:
    path = tmp_path / "m.kvmap"
    save_map(path, make_map(**SMALL), backend_info=backend_info(layers=1, heads=1, head_dim=4),
             tracker_config_json='{"keyframing": {"view_angle_deg": 10.0}}', mode="object")  # fmt: skip
    metadata = split_file(path.read_bytes())[0]["__metadata__"]
    assert metadata["format_version"] == str(FORMAT_VERSION) and "mode" not in metadata
    assert json.loads(metadata["tracker_config"])["mode"] == "object"
    assert read_map_info(path).mode == "object"
    for edit, match in (
        (lambda h: h["__metadata__"].update(mode="object"), "keeps the mode in 'tracker_config'"),
        (lambda h: h["__metadata__"].update(tracker_config="{}"), "tracker_config mode must be"),
    ):
        edited = tmp_path / "edited.kvmap"
        edited.write_bytes(rewrite_header(path.read_bytes(), edit))
        with pytest.raises(MapFormatError, match=match):
            read_map_info(edited)
    with pytest.raises(MapFormatError, match="but the tracker config says 'object'"):
        save_map(tmp_path / "x.kvmap", make_map(**SMALL),
                 backend_info=backend_info(layers=1, heads=1, head_dim=4),
                 tracker_config_json=TRACKER_CONFIG, mode="scene")  # fmt: skip

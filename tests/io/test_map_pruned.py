"""Pruned maps in files: per-layer lengths and kept token indices round-trip (also in a new
process), take fewer bytes, and a tampered index list is a typed error."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.cache.pruning import prune_cache
from kvtracker_sdk.errors import MapCorruptedError, MapFormatError
from kvtracker_sdk.io.map_file.map_file import load_map, read_map_info, save_map
from tests.helpers import PROJECT_ROOT
from tests.io.map_factory import (
    EXTRA_TOKENS,
    TRACKER_CONFIG,
    backend_info,
    compact_maps_match,
    make_map,
    map_digest,
    maps_equal,
    rewrite_header,
    split_file,
)


def pruned_map() -> KeyframeMap:
    keyframe_map = make_map(num_keyframes=4)
    prune_cache(keyframe_map.cache, keep_ratio=0.5, extra_tokens_per_frame=EXTRA_TOKENS)
    return keyframe_map


def save(path: Path, keyframe_map: KeyframeMap) -> Path:
    save_map(
        path, keyframe_map, backend_info=backend_info(), tracker_config_json=TRACKER_CONFIG,
        mode="object",
    )  # fmt: skip
    return path


_CHILD = """
import json, sys
from kvtracker_sdk.io.map_file.map_file import load_map
from tests.io.map_factory import map_digest
print(json.dumps(map_digest(load_map(sys.argv[1]).keyframe_map)))
"""


def test_a_pruned_map_round_trips_in_a_new_process_and_is_smaller(tmp_path: Path) -> None:
    original = pruned_map()
    path = save(tmp_path / "pruned.kvmap", original)
    full = save(tmp_path / "full.kvmap", make_map(num_keyframes=4))
    loaded = load_map(path).keyframe_map
    assert loaded.cache.pruned and maps_equal(loaded, original)
    info = read_map_info(path)
    assert info.layer_lengths == tuple(
        original.cache.layer_length(i) for i in range(original.cache.layout.num_layers)
    )
    assert info.cache_nbytes == original.cache.nbytes < read_map_info(full).cache_nbytes
    assert path.stat().st_size < full.stat().st_size
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, str(path)],
        cwd=PROJECT_ROOT, capture_output=True, text=True, timeout=120, check=True,
    )  # fmt: skip
    assert json.loads(out.stdout) == json.loads(json.dumps(map_digest(original)))


def test_an_unpruned_map_has_no_layer_lengths(tmp_path: Path) -> None:
    path = save(tmp_path / "full.kvmap", make_map())
    assert read_map_info(path).layer_lengths is None
    assert not load_map(path).keyframe_map.cache.pruned


def test_tampered_kept_tokens_are_typed_errors(tmp_path: Path) -> None:
    path = save(tmp_path / "pruned.kvmap", pruned_map())
    data = path.read_bytes()
    header, _ = split_file(data)
    begin = header["layers.0.kept_tokens"]["data_offsets"][0]
    offset = len(data) - len(split_file(data)[1]) + begin
    flipped = bytearray(data)
    flipped[offset] ^= 0xFF  # the first index becomes out of range
    bad = tmp_path / "flipped.kvmap"
    bad.write_bytes(bytes(flipped))
    with pytest.raises(MapCorruptedError, match="kept_tokens"):
        load_map(bad)
    with pytest.raises(MapCorruptedError, match="kept token indices"):
        load_map(bad, verify_checksums=False)

    def lengths(h: dict) -> None:
        h["__metadata__"]["layer_lengths"] = json.dumps([10**6] * 4)

    wrong = tmp_path / "lengths.kvmap"
    wrong.write_bytes(rewrite_header(data, lengths))
    with pytest.raises(MapFormatError, match="layer_lengths"):
        load_map(wrong)


def test_a_pruned_int8_map_round_trips(tmp_path: Path) -> None:
    keyframe_map = pruned_map()
    quantized = replace(keyframe_map, cache=keyframe_map.cache.to(storage="int8"))
    path = save(tmp_path / "pruned_int8.kvmap", quantized)
    info = read_map_info(path)
    assert info.format_version == 4 and info.dtype == "int8" and info.layer_lengths is not None
    loaded = load_map(path).keyframe_map
    assert loaded.cache.pruned and loaded.cache.quantized and compact_maps_match(loaded, quantized)
    assert info.cache_nbytes == quantized.cache.nbytes < keyframe_map.cache.nbytes

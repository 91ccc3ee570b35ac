"""Map files of quantised caches (format version 3: compact keyframes; 2 without), and maps of
every older version.

A quantised map saved by the golden Pi3 and loaded in a new process tracks bit for bit as its
cache did before saving, and its keyframe points come back within float16's rounding. The old-version fixtures are made here, not committed: a dense map is written as version 1 (the
oldest version that holds it), and a version-1 file is also rebuilt from a new one by editing its
header (re-sealed), so each readable version is loaded from bytes this test wrote.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.cache.keyframe_map import Keyframe, KeyframeMap
from kvtracker_sdk.errors import MapFormatError
from kvtracker_sdk.eval.cache_deviation import tum_frames
from kvtracker_sdk.geometry.sim3 import Sim3
from kvtracker_sdk.io.map_file.map_file import load_map, read_map_info, save_map
from kvtracker_sdk.io.map_file.map_schema import FORMAT_VERSION
from kvtracker_sdk.io.sources.sources import TumSource
from kvtracker_sdk.types import HeadSet
from tests.helpers import PROJECT_ROOT, shared_path
from tests.io.map_factory import (
    POINTS_RTOL,
    TRACKER_CONFIG,
    backend_info,
    compact_maps_match,
    make_map,
    maps_equal,
    rewrite_header,
)

STORAGES = ("int8", "float8_e4m3fn")


def _save(
    path: Path, storage: str | None = None, dtype: str = "float32", compact: bool | None = None
) -> Path:
    keyframe_map = make_map(dtype=getattr(torch, dtype), storage=storage)
    save_map(path, keyframe_map, backend_info=backend_info(dtype=dtype),
             tracker_config_json=TRACKER_CONFIG, mode="object", compact_keyframes=compact)  # fmt: skip
    return path


@pytest.mark.parametrize("storage", STORAGES)
def test_a_quantised_map_round_trips_with_its_cache_bit_for_bit(tmp_path: Path, storage: str) -> None:
    path = _save(tmp_path / "q.kvmap", storage)
    info = read_map_info(path)
    assert info.format_version == FORMAT_VERSION and info.dtype == storage and info.quantized
    assert info.keyframe_encoding == "compact-xyz"  # the factory's points are not pinhole rays
    loaded = load_map(path).keyframe_map
    assert loaded.cache.storage == storage and loaded.cache.dtype == torch.float32
    # cache, images, masks, poses bit for bit; confidences / points within the stated bounds
    assert compact_maps_match(loaded, make_map(storage=storage))
    assert not maps_equal(loaded, make_map(storage=storage))  # the points did change
    full = _save(tmp_path / "full.kvmap", storage, compact=False)  # the full keyframe payload
    assert read_map_info(full).keyframe_encoding == "full"
    assert maps_equal(load_map(full).keyframe_map, make_map(storage=storage))


def test_quantised_maps_are_at_least_1_9x_smaller_than_bf16(tmp_path: Path) -> None:
    bf16 = read_map_info(_save(tmp_path / "bf16.kvmap", dtype="bfloat16"))
    for storage in STORAGES:
        info = read_map_info(_save(tmp_path / f"{storage}.kvmap", storage))
        # head_dim 8 here: 8 data bytes + 1 scale byte per token and head, vs 16 in bf16
        assert bf16.cache_nbytes / info.cache_nbytes == pytest.approx(16 / 9)
        assert info.cache_nbytes == make_map(storage=storage).cache.nbytes
    big = make_map(head_dim=64, storage="int8").cache  # the real models' head_dim
    assert make_map(head_dim=64, dtype=torch.bfloat16).cache.nbytes / big.nbytes >= 1.9


def test_a_backend_dtype_changes_the_compute_dtype_not_the_stored_data(tmp_path: Path) -> None:
    path = _save(tmp_path / "q.kvmap", "int8")
    cache = load_map(path, expected_backend=backend_info(dtype="bfloat16")).keyframe_map.cache
    assert cache.storage == "int8" and cache.dtype == torch.bfloat16
    assert cache.to(dtype=torch.float32).equals(make_map(storage="int8").cache)


def test_every_map_is_written_as_the_current_version(tmp_path: Path) -> None:
    """Older versions load (``test_map_versions.py``); the writer writes the current one only."""
    for name, storage, compact in (("dense", None, None), ("full", "int8", False), ("q", "int8", None)):
        info = read_map_info(_save(tmp_path / f"{name}.kvmap", storage, compact=compact))
        assert info.format_version == FORMAT_VERSION


def test_a_quantised_cache_needs_version_2_and_its_scale_description(tmp_path: Path) -> None:
    path = _save(tmp_path / "q.kvmap", "int8")
    edits = {
        "version 1": lambda h: h["__metadata__"].update(format_version="1"),
        "no description": lambda h: h["__metadata__"].pop("cache_quantization"),
        "other scales": lambda h: h["__metadata__"].update(cache_quantization=json.dumps(
            {"scale_dtype": "float16", "key_scale": "token_head", "value_scale": "token_head"})),
    }  # fmt: skip
    for name, edit in edits.items():
        broken = tmp_path / f"{name}.kvmap"
        broken.write_bytes(rewrite_header(path.read_bytes(), edit))
        with pytest.raises(MapFormatError):
            read_map_info(broken)
    dense = _save(tmp_path / "dense.kvmap")
    extra = tmp_path / "extra.kvmap"
    extra.write_bytes(rewrite_header(dense.read_bytes(), lambda h: h["__metadata__"].update(
        cache_quantization=json.dumps({"scale_dtype": "float8_e5m2"}))))  # fmt: skip
    with pytest.raises(MapFormatError, match="has no 'cache_quantization'"):
        read_map_info(extra)


_TRACK_CHILD = """
import hashlib, json, sys
import numpy as np, torch
torch.set_num_threads(1)
from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.io.map_file.map_file import load_map
from kvtracker_sdk.types import HeadSet
path, weights, frame = sys.argv[1:4]
backend = TorchBackend.from_pretrained(weights)
kf_map = load_map(path, expected_backend=backend.info).keyframe_map
result = backend.track(np.load(frame), kf_map.cache, heads=HeadSet.ALL)
keyframe_points = np.stack([kf.local_points for kf in kf_map.keyframes])
print(json.dumps({"storage": kf_map.cache.storage, "pose": result.pose.tobytes().hex(),
                  "points": hashlib.sha256(result.local_points.tobytes()).hexdigest(),
                  "keyframe_points": hashlib.sha256(keyframe_points.tobytes()).hexdigest()}))
"""


def test_a_quantised_map_tracks_identically_in_a_new_process(tmp_path: Path) -> None:
    storage = "int8"  # fp8 maps take the same path (their round trip is bit for bit above)
    weights = shared_path("golden", "pi3", "weights.safetensors")
    frames = tum_frames(list(TumSource(shared_path("data", "tum_fr2_desk")))[:3], "pi3",
                        resolution=224)  # fmt: skip
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the child's count: the same kernels, bit for bit
    try:
        backend = TorchBackend.from_pretrained(weights)
        mapped = backend.map(frames[:2])
        cache = mapped.cache.to(storage=storage)
        keyframes = tuple(
            Keyframe(keyframe_id=i, frame_index=i, timestamp=None, image=frames[i], mask=None,
                     T_world_cam=mapped.poses[i], confidence_map=mapped.confidence[i],
                     local_points=mapped.local_points[i],
                     mean_confidence=float(mapped.confidence[i].mean()))
            for i in range(2)
        )  # fmt: skip
        keyframe_map = KeyframeMap(keyframes, cache, Sim3.identity(), generation=1,
                                   resolution=frames.shape[1:3])  # fmt: skip
        path = tmp_path / "golden.kvmap"
        save_map(path, keyframe_map, backend_info=backend.info, tracker_config_json="{}",
                 mode="scene")  # fmt: skip
        here = backend.track(frames[2], cache, heads=HeadSet.ALL)
    finally:
        torch.set_num_threads(threads)
    np.save(tmp_path / "frame.npy", frames[2])
    out = subprocess.run(
        [sys.executable, "-c", _TRACK_CHILD, str(path), str(weights), str(tmp_path / "frame.npy")],
        cwd=PROJECT_ROOT, capture_output=True, text=True, timeout=120, check=True,
    )  # fmt: skip
    child = json.loads(out.stdout)
    assert child["storage"] == storage
    assert child["pose"] == here.pose.tobytes().hex()
    assert here.local_points is not None
    assert child["points"] == hashlib.sha256(here.local_points.tobytes()).hexdigest()
    # the keyframes' compact points: the same bits in both processes, float16-close to the pass's
    assert read_map_info(path).keyframe_encoding == "compact-xyz"
    loaded = np.stack([kf.local_points for kf in load_map(path).keyframe_map.keyframes])
    assert child["keyframe_points"] == hashlib.sha256(loaded.tobytes()).hexdigest()
    original = mapped.local_points[:2]
    assert np.all(np.abs(loaded - original) <= POINTS_RTOL * np.abs(original))
    assert not np.array_equal(loaded, original)

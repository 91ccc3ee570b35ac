"""Seeded version-2/3 map files with one impossible number, checksums recomputed (as anyone
editing a file can): quantisation scales (zero, negative, subnormal, infinite, NaN), gauges
(scale, translation), keyframe translations and int8 data outside what the quantiser writes.

Shared by ``test_map_impossible_values.py`` (a few hundred cases) and
``benchmarks/fuzz_inputs.py`` (more, each in a fresh process).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from kvtracker_sdk.io.map_file.map_file import save_map
from kvtracker_sdk.io.map_file.map_format import metadata_digest
from tests.io.map_factory import TRACKER_CONFIG, backend_info, join_file, make_map, split_file

# (storage, compact keyframes): version 3 and version 2 files of both quantised dtypes
BASES = (("int8", True), ("int8", False), ("float8_e4m3fn", True), ("float8_e4m3fn", False))
# float8 e5m2 bytes no quantiser writes: +-0, subnormals, negatives, inf, NaN
_E5M2_BAD = {
    "zero": [0x00, 0x80],
    "subnormal": [0x01, 0x02, 0x03],
    "negative": [0x84, 0xBC, 0xC0, 0xFB],
    "inf": [0x7C, 0xFC],
    "nan": [0x7D, 0x7E, 0x7F, 0xFF],
}
_GAUGE_SCALES = [1e308, 1e300, 1e7, 1e-7, 1e-300, 5e-324]
_TRANSLATIONS = [1e308, -1e300, 1e7, -2e6]


def base_files(folder: Path) -> dict[tuple[str, bool], bytes]:
    """The four benign quantised maps (bytes), saved once."""
    files = {}
    for storage, compact in BASES:
        path = folder / f"{storage}-{int(compact)}.kvmap"
        save_map(path, make_map(storage=storage), backend_info=backend_info(),
                 tracker_config_json=TRACKER_CONFIG, mode="object", compact_keyframes=compact)
        files[(storage, compact)] = path.read_bytes()
    return files


def _reseal(header: dict, body: bytearray, names: list[str]) -> bytes:
    """Recompute the sha256 of the tensors ``names`` and the metadata digest."""
    metadata = header["__metadata__"]
    digests = json.loads(metadata["tensor_sha256"])
    for name in names:
        start, stop = header[name]["data_offsets"]
        digests[name] = hashlib.sha256(bytes(body[start:stop])).hexdigest()
    metadata["tensor_sha256"] = json.dumps(digests, separators=(",", ":"))
    metadata["metadata_sha256"] = metadata_digest(metadata)
    return join_file(header, bytes(body))


def _edit_scale(data: bytes, rng: np.random.Generator) -> tuple[str, bytes]:
    header, body = split_file(data)
    body = bytearray(body)
    names = sorted(k for k in header if k.startswith("layers.") and k.endswith("_scale"))
    name = names[rng.integers(len(names))]
    kind = sorted(_E5M2_BAD)[rng.integers(len(_E5M2_BAD))]
    start, stop = header[name]["data_offsets"]
    for _ in range(int(rng.integers(1, 4))):  # one to three scales of the tensor
        body[int(rng.integers(start, stop))] = int(rng.choice(_E5M2_BAD[kind]))
    return f"scale-{kind}-{name}", _reseal(header, body, [name])


def _edit_gauge(data: bytes, rng: np.random.Generator) -> tuple[str, bytes]:
    header, body = split_file(data)
    gauge = json.loads(header["__metadata__"]["gauge"])
    if rng.random() < 0.6:
        gauge["scale"] = float(rng.choice(_GAUGE_SCALES))
        what = f"gauge-scale-{gauge['scale']:g}"
    else:
        gauge["translation"][int(rng.integers(3))] = float(rng.choice(_TRANSLATIONS))
        what = "gauge-translation"
    header["__metadata__"]["gauge"] = json.dumps(gauge)
    return what, _reseal(header, bytearray(body), [])


_POINT_SCALES = [0.0, -1.0, 3.0, 0.3, float("inf"), float("nan"), 2.0**120, 1e-45]


def _edit_points_scale(data: bytes, rng: np.random.Generator) -> tuple[str, bytes]:
    """A compact map's per-keyframe points scale (the encoder writes powers of two)."""
    header, body = split_file(data)
    body = bytearray(body)
    name = "keyframes.points_scale"
    start, stop = header[name]["data_offsets"]
    scales = np.frombuffer(bytes(body[start:stop]), dtype=np.float32).copy()
    scales[int(rng.integers(len(scales)))] = np.float32(rng.choice(_POINT_SCALES))
    body[start:stop] = scales.tobytes()
    return "points-scale", _reseal(header, body, [name])


def _edit_pose(data: bytes, rng: np.random.Generator) -> tuple[str, bytes]:
    header, body = split_file(data)
    body = bytearray(body)
    name = "keyframes.T_world_cam"
    start, _ = header[name]["data_offsets"]
    poses = np.frombuffer(bytes(body[start:start + 3 * 128]), dtype=np.float64).reshape(3, 4, 4).copy()
    poses[int(rng.integers(3)), int(rng.integers(3)), 3] = float(rng.choice(_TRANSLATIONS))
    body[start:start + poses.nbytes] = poses.tobytes()
    return "keyframe-translation", _reseal(header, body, [name])


def _edit_int8(data: bytes, rng: np.random.Generator) -> tuple[str, bytes]:
    header, body = split_file(data)
    body = bytearray(body)
    names = sorted(k for k in header if k.endswith((".key", ".value")))
    name = names[rng.integers(len(names))]
    start, stop = header[name]["data_offsets"]
    body[int(rng.integers(start, stop))] = 0x80  # int8 -128: the quantiser clamps to [-127, 127]
    return f"int8-minus-128-{name}", _reseal(header, body, [name])


def impossible_maps(
    bases: dict[tuple[str, bool], bytes], count: int, seed: int
) -> Iterator[tuple[str, bytes]]:
    """``count`` seeded (name, file bytes) cases, spread over the bases and edit kinds."""
    rng = np.random.default_rng(seed)
    keys = sorted(bases)
    for index in range(count):
        storage, compact = keys[index % len(keys)]
        data = bases[(storage, compact)]
        roll = rng.random()
        if roll < 0.55:
            name, edited = _edit_scale(data, rng)
        elif roll < 0.8:
            name, edited = _edit_gauge(data, rng)
        elif roll < 0.87 and compact:
            name, edited = _edit_points_scale(data, rng)
        elif roll < 0.93 or storage != "int8":
            name, edited = _edit_pose(data, rng)
        else:
            name, edited = _edit_int8(data, rng)
        yield f"{storage}-v{3 if compact else 2}-{index}-{name}", edited


__all__ = ["BASES", "base_files", "impossible_maps", "torch"]

"""The compact keyframe payload of quantised maps (``io/map_file/keyframe_codec.py``, format version 3).

Bounds (stated in the codec's docstring): masks and images exact, confidences within half a
uint16 step, points within float16's relative rounding 2**-11 (DA3-style depth x ray: the
same bound plus float32 rounding of the ray slope, 1e-6 relative, in ``POINTS_RTOL``).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from kvtracker_sdk.errors import MapCorruptedError
from kvtracker_sdk.io.map_file.keyframe_codec import decode_compact, encode_compact
from kvtracker_sdk.io.map_file.map_file import load_map, read_map_info, save_map
from kvtracker_sdk.models.da3.conventions import unproject_depth
from tests.io.map_factory import (
    CONFIDENCE_ATOL,
    POINTS_RTOL,
    TRACKER_CONFIG,
    backend_info,
    compact_maps_match,
    make_map,
)

SIZE = (14, 21)


def _payload(points: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    n, h, w = points.shape[:3]
    confidence = rng.random((n, h, w), dtype=np.float32)
    confidence[0, 0, :2] = (0.0, 1.0)  # the ends stay exact
    return rng.random((n, h, w)) > 0.5, confidence, points


def _da3_points(n: int, scale: float) -> np.ndarray:
    """Points made as DA3 makes them: depth x K^-1 (u, v, 1), then times the gauge's scale."""
    rng = np.random.default_rng(1)
    depth = torch.from_numpy(rng.uniform(0.5, 8.0, (n, *SIZE)).astype(np.float32))
    K = torch.tensor([[[20.0, 0, 10.5], [0, 19.0, 7.0], [0, 0, 1]]] * n, dtype=torch.float64)
    return unproject_depth(depth, K).numpy() * np.float32(scale)


def _round_trip(payload: tuple[np.ndarray, ...]) -> tuple[str, int, tuple[np.ndarray, ...]]:
    encoding, tensors = encode_compact(*payload)
    nbytes = sum(t.numel() * t.element_size() for t in tensors.values())
    return encoding, nbytes, decode_compact(tensors, encoding, SIZE, "test")


def test_masks_confidences_and_points_come_back_within_the_stated_bounds() -> None:
    rng = np.random.default_rng(2)
    points = rng.normal(size=(2, *SIZE, 3)).astype(np.float32)
    points[0] *= 1e6  # far beyond float16's range: the power-of-two scale keeps it finite
    points[1, 0, 0] = (np.nan, np.inf, 1e-3)
    payload = _payload(points)
    encoding, nbytes, (masks, confidence, decoded) = _round_trip(payload)
    assert encoding == "compact-xyz" and decoded.dtype == np.float32 == confidence.dtype
    assert np.array_equal(masks, payload[0])
    assert np.abs(confidence - payload[1]).max() <= CONFIDENCE_ATOL
    assert confidence[0, 0, 0] == 0.0 and confidence[0, 0, 1] == 1.0
    finite = np.isfinite(points)
    assert np.array_equal(np.isfinite(decoded), finite) and np.isnan(decoded[1, 0, 0, 0])
    error = np.abs(decoded[finite] - points[finite])
    assert np.all(error <= POINTS_RTOL * np.abs(points[finite]))
    pixels = points.shape[0] * SIZE[0] * SIZE[1]
    assert nbytes <= pixels * (1 / 8 + 2 + 6) + 2 * (4 + 1)  # mask, confidence, xyz (+ scales): full is 17


@pytest.mark.parametrize("scale", [1.0, 3.7e-3])
def test_da3_style_points_are_stored_as_depth_and_rays(scale: float) -> None:
    points = _da3_points(2, scale)
    payload = _payload(points)
    encoding, nbytes, (_, _, decoded) = _round_trip(payload)
    assert encoding == "compact-depth"
    assert np.all(np.abs(decoded - points) <= POINTS_RTOL * np.abs(points))
    pixels = points.shape[0] * SIZE[0] * SIZE[1]
    assert nbytes <= pixels * (2 + 2 + 1 / 8) + 2 * (4 + 1 + 4 * sum(SIZE))  # depth, conf, mask, rays
    broken = points.copy()
    broken[0, 3, 4, 0] *= 1.001  # one point off its ray: stored as xyz
    assert _round_trip(_payload(broken))[0] == "compact-xyz"


def test_a_whole_int8_map_is_1_9x_smaller_than_bf16_and_loads_back(tmp_path: Path) -> None:
    sizes = {}
    # Pi3 mid's K/V per pixel (8 cached layers x 384 channels, 5 registers, patch 14)
    for name, storage, dtype in (("bf16", None, torch.bfloat16), ("int8", "int8", torch.float32)):
        keyframe_map = make_map(num_keyframes=2, layers=8, heads=6, head_dim=64, size=(56, 70),
                                storage=storage, dtype=dtype)  # fmt: skip
        path = tmp_path / f"{name}.kvmap"
        save_map(path, keyframe_map, backend_info=backend_info(layers=8, heads=6, head_dim=64,
                 dtype=str(dtype).removeprefix("torch.")), tracker_config_json=TRACKER_CONFIG,
                 mode="object")  # fmt: skip
        sizes[name] = path.stat().st_size
        if storage is not None:
            assert compact_maps_match(load_map(path).keyframe_map, keyframe_map)
    assert read_map_info(tmp_path / "bf16.kvmap").keyframe_encoding == "full"
    assert sizes["bf16"] / sizes["int8"] >= 1.9


def test_a_bad_point_scale_is_a_typed_error(tmp_path: Path) -> None:
    keyframe_map = make_map(storage="int8")
    _, tensors = encode_compact(
        np.zeros((3, 28, 42), bool),
        np.stack([kf.confidence_map for kf in keyframe_map.keyframes]),
        np.stack([kf.local_points for kf in keyframe_map.keyframes]),
    )
    tensors["keyframes.points_scale"][1] = 0.0
    with pytest.raises(MapCorruptedError, match="point scales"):
        decode_compact(tensors, "compact-xyz", (28, 42), "test")
    # and the saver refuses nothing it made itself: a DA3-style map round-trips as compact-depth
    da3 = replace(keyframe_map, keyframes=tuple(
        replace(kf, local_points=_da3_points(1, 0.5)[0].repeat(2, 0).repeat(2, 1))
        for kf in keyframe_map.keyframes))  # fmt: skip
    path = tmp_path / "da3.kvmap"
    save_map(path, da3, backend_info=backend_info(), tracker_config_json=TRACKER_CONFIG,
             mode="object")  # fmt: skip
    assert read_map_info(path).keyframe_encoding == "compact-depth"
    assert compact_maps_match(load_map(path).keyframe_map, da3)

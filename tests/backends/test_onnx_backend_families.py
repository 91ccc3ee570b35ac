"""OnnxBackend on each family's session export against TorchBackend on the same golden weights:
identity, mapping pass, tracking on a map made by either runtime.

Both backends compute fp32; they may differ by float rounding only: poses atol 1e-5, confidence
atol 1e-5, K/V atol 1e-5, local points atol 1e-4 + rtol 1e-4 (the golden tolerances). The tests
only one family needs are in ``test_onnx.py`` (Pi3) and ``test_onnx_da3.py``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from kvtracker_sdk.backends.base import Backend, MapResult
from kvtracker_sdk.backends.onnx import OnnxBackend
from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.types import HeadSet
from tests.conftest import OnnxExport


@dataclass(frozen=True)
class Case:
    size: tuple[int, int]  # (H, W) of the test images: not the export's check size
    tokens_per_frame: int
    model: str
    seed: int  # of the random images


CASES = {
    "pi3": Case((112, 154), 5 + 8 * 11, "pi3-custom", 0),
    "da3": Case((98, 196), 1 + 7 * 14, "da3-custom", 3),
}


@dataclass(frozen=True)
class Runtimes:
    family: str
    onnx: OnnxBackend
    torch: TorchBackend
    images: np.ndarray  # uint8 [4, H, W, 3]: three keyframes and a query
    onnx_map: MapResult
    torch_map: MapResult


@pytest.fixture(scope="module", params=sorted(CASES))
def runtimes(
    request: pytest.FixtureRequest, onnx_exports: Callable[[str], OnnxExport]
) -> Runtimes:
    family = str(request.param)
    export, case = onnx_exports(family), CASES[family]
    onnx_backend = OnnxBackend(export.folder, threads=1)
    torch_backend = TorchBackend.from_pretrained(export.weights)
    images = np.random.default_rng(case.seed).integers(0, 256, (4, *case.size, 3), np.uint8)
    return Runtimes(
        family,
        onnx_backend,
        torch_backend,
        images,
        onnx_backend.map(images[:3]),
        torch_backend.map(images[:3]),
    )


def test_info_equals_the_torch_backends(runtimes: Runtimes) -> None:
    info, reference = runtimes.onnx.info, runtimes.torch.info
    case = CASES[runtimes.family]
    assert isinstance(runtimes.onnx, Backend)
    assert (info.backend, info.family, info.model, info.dtype, info.device) == (
        "onnx", runtimes.family, case.model, "float32", "cpu",
    )  # fmt: skip
    assert info.fingerprint == reference.fingerprint  # caches and maps cross between them
    assert info.layout == reference.layout
    assert (info.config_hash, info.weights_fingerprint) == (
        reference.config_hash,
        reference.weights_fingerprint,
    )
    assert info.tokens_per_frame(*case.size) == reference.tokens_per_frame(*case.size)
    assert info.tokens_per_frame(*case.size) == case.tokens_per_frame
    assert info.accelerations == ("CPUExecutionProvider",)


def test_map_matches_torch(runtimes: Runtimes) -> None:
    onnx_map, torch_map = runtimes.onnx_map, runtimes.torch_map
    height, width = CASES[runtimes.family].size
    assert onnx_map.poses.dtype == np.float64 and onnx_map.poses.shape == (3, 4, 4)
    assert onnx_map.confidence.dtype == np.float32
    assert onnx_map.confidence.shape == (3, height, width)
    assert onnx_map.local_points.dtype == np.float32 and not onnx_map.poses.flags.writeable
    np.testing.assert_allclose(onnx_map.poses, torch_map.poses, atol=1e-5, rtol=0)
    np.testing.assert_allclose(onnx_map.confidence, torch_map.confidence, atol=1e-5, rtol=0)
    np.testing.assert_allclose(onnx_map.local_points, torch_map.local_points, atol=1e-4, rtol=1e-4)
    cache, reference = onnx_map.cache, torch_map.cache
    assert (cache.keyframe_ids, cache.tokens_per_frame, cache.dtype) == (
        (0, 1, 2),
        CASES[runtimes.family].tokens_per_frame,
        torch.float32,
    )
    for layer in range(cache.layout.num_layers):
        torch.testing.assert_close(cache.keys(layer), reference.keys(layer), atol=1e-5, rtol=0)
        torch.testing.assert_close(cache.values(layer), reference.values(layer), atol=1e-5, rtol=0)
    assert onnx_map.timings_ms["map"] > 0


@pytest.mark.parametrize("heads", list(HeadSet))
def test_track_on_either_backends_map_matches_torch(runtimes: Runtimes, heads: HeadSet) -> None:
    query = runtimes.images[3]
    expected = runtimes.torch.track(query, runtimes.torch_map.cache, heads=heads)
    before = runtimes.onnx_map.cache.clone()
    for cache in (runtimes.onnx_map.cache, runtimes.torch_map.cache):  # a map by either runtime
        result = runtimes.onnx.track(query, cache, heads=heads)
        np.testing.assert_allclose(result.pose, expected.pose, atol=1e-5, rtol=0)
        assert (result.confidence is None) == (heads is HeadSet.CAMERA)
        if result.confidence is not None:
            assert result.confidence == pytest.approx(expected.confidence, abs=1e-5)
            np.testing.assert_allclose(result.confidence_map, expected.confidence_map, atol=1e-5)
        assert (result.local_points is None) == (heads is not HeadSet.ALL)
        if result.local_points is not None:
            np.testing.assert_allclose(
                result.local_points, expected.local_points, atol=1e-4, rtol=1e-4
            )
        assert result.timings_ms["track"] > 0 and not result.pose.flags.writeable
    assert runtimes.onnx_map.cache.equals(before)  # tracking only reads the cache

"""TorchBackend over each family's small random network: identity, head sets, bf16 (the tests
both families share; family-specific ones in ``test_torch_backend.py`` (Pi3) and
``test_torch_backend_da3.py``)."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from torch import nn

from kvtracker_sdk.backends.base import Backend
from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.cache.kv_cache import CacheLayout
from kvtracker_sdk.errors import BackendMismatchError, ConfigError, ModelError
from kvtracker_sdk.types import HeadSet
from tests.models.da3.factories import random_da3
from tests.models.pi3.factories import random_pi3

H, W = 28, 42  # a 2x3 patch grid
FACTORIES = {"pi3": random_pi3, "da3": random_da3}
# family -> (extra tokens per frame, cache layout of the factory's default network)
EXPECTED = {"pi3": (5, CacheLayout((1, 3), 2, 16)), "da3": (1, CacheLayout((3, 5), 2, 8))}


@pytest.fixture(scope="module", params=sorted(FACTORIES))
def family(request: pytest.FixtureRequest) -> str:
    return str(request.param)


@pytest.fixture(scope="module")
def model(family: str) -> nn.Module:
    return FACTORIES[family](seed=7)


@pytest.fixture(scope="module")
def backend(model: nn.Module) -> TorchBackend:
    return TorchBackend(copy.deepcopy(model), model_name="tiny")


@pytest.fixture(scope="module")
def images() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, size=(4, H, W, 3), dtype=np.uint8)


def test_info(backend: TorchBackend, model: nn.Module, family: str) -> None:
    info = backend.info
    assert isinstance(backend, Backend)
    assert (info.backend, info.family, info.model) == ("torch", family, "tiny")
    extra_tokens, layout = EXPECTED[family]
    assert info.patch_size == 14 and info.extra_tokens_per_frame == extra_tokens
    assert info.tokens_per_frame(H, W) == extra_tokens + 6 and info.layout == layout
    assert (info.dtype, info.device) == ("float32", "cpu")
    assert info.config_hash == model.config.config_hash  # type: ignore[union-attr]
    assert "sdpa" in info.accelerations
    bf16 = TorchBackend(copy.deepcopy(model), dtype="bf16", model_name="tiny")
    assert bf16.info.dtype == "bfloat16"
    assert bf16.info.fingerprint == info.fingerprint  # same function family, config and weights
    other = TorchBackend(FACTORIES[family](seed=8), model_name="tiny")
    assert other.info.fingerprint != info.fingerprint
    with pytest.raises(ConfigError, match="float32 or bfloat16"):
        TorchBackend(copy.deepcopy(model), dtype=torch.float16)
    with pytest.raises(ModelError, match="neither a Pi3 nor a DepthAnything3"):
        TorchBackend(torch.nn.Linear(2, 2))


@pytest.mark.parametrize("heads", list(HeadSet))
def test_track_heads(backend: TorchBackend, images: np.ndarray, heads: HeadSet) -> None:
    cache = backend.map(images[:3]).cache
    result = backend.track(images[3], cache, heads=heads)
    assert result.pose.shape == (4, 4) and result.pose.dtype == np.float64
    assert (result.confidence is None) == (heads is HeadSet.CAMERA)
    assert (result.local_points is None) == (heads is not HeadSet.ALL)
    if result.confidence_map is not None:
        assert result.confidence_map.shape == (H, W)
        assert result.confidence == pytest.approx(float(result.confidence_map.mean()))
    reference = backend.track(images[3], cache, heads=HeadSet.ALL)
    np.testing.assert_array_equal(result.pose, reference.pose)
    batch = backend.track_batch(images[2:], cache, heads=heads)
    np.testing.assert_allclose(batch[1].pose, result.pose, atol=1e-6)


def test_bf16_backend(model: nn.Module, images: np.ndarray, backend: TorchBackend) -> None:
    bf16 = TorchBackend(copy.deepcopy(model), dtype=torch.bfloat16)
    mapped = bf16.map(images[:3])
    assert mapped.cache.dtype == torch.bfloat16
    result = bf16.track(images[3], mapped.cache, heads=HeadSet.ALL)
    assert result.pose.dtype == np.float64 and np.isfinite(result.local_points).all()  # type: ignore[arg-type]
    reference = backend.track(images[3], backend.map(images[:3]).cache)
    # random tiny model: bf16 stays within 0.1 of fp32 in pose entries
    np.testing.assert_allclose(result.pose, reference.pose, atol=0.1)
    with pytest.raises(BackendMismatchError, match=r"cache\.to"):
        backend.track(images[3], mapped.cache)

"""TorchBackend serving Depth Anything 3: SDK conventions and family selection (identity, heads
and bf16 of both families: ``test_torch_backend_families.py``)."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.cache.kv_cache import CacheLayout
from kvtracker_sdk.errors import BackendMismatchError
from kvtracker_sdk.models.da3 import DepthAnything3, load_da3, to_sdk
from kvtracker_sdk.types import HeadSet
from tests.helpers import shared_path
from tests.models.da3.factories import random_da3

H, W = 28, 42  # a 2x3 patch grid: 1 camera token + 6 patches = 7 tokens per frame


@pytest.fixture(scope="module")
def model() -> DepthAnything3:
    return random_da3(seed=7)


@pytest.fixture(scope="module")
def backend(model: DepthAnything3) -> TorchBackend:
    return TorchBackend(copy.deepcopy(model))


@pytest.fixture(scope="module")
def images() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, size=(4, H, W, 3), dtype=np.uint8)


@torch.no_grad()
def test_map_in_sdk_conventions(
    backend: TorchBackend, model: DepthAnything3, images: np.ndarray
) -> None:
    result = backend.map(images[:3])
    assert result.poses.shape == (3, 4, 4) and result.poses.dtype == np.float64
    np.testing.assert_allclose(np.linalg.det(result.poses[:, :3, :3]), 1.0, atol=1e-6)
    assert result.confidence.shape == (3, H, W) and result.confidence.dtype == np.float32
    assert result.confidence.min() >= 0.0 and result.confidence.max() < 1.0
    assert result.local_points.shape == (3, H, W, 3) and (result.local_points[..., 2] > 0).all()
    assert (result.cache.num_keyframes, result.cache.tokens_per_frame) == (3, 7)
    frames = torch.from_numpy(images[:3]).permute(0, 3, 1, 2).float().unsqueeze(0) / 255.0
    reference = model.forward_map(frames, heads=HeadSet.CONFIDENCE)
    np.testing.assert_allclose(
        result.poses, to_sdk(reference.output).T_world_cam[0].numpy(), atol=1e-6
    )
    torch.testing.assert_close(result.cache.keys(1), reference.keys[1], atol=1e-6, rtol=0)
    # DA3's extrinsics are world-to-camera: the backend's poses are their inverses
    world_to_cam = reference.output.extrinsics[0].double().numpy()
    np.testing.assert_allclose(
        world_to_cam[:, :3, :3] @ result.poses[:, :3, :3],
        np.broadcast_to(np.eye(3), (3, 3, 3)),
        atol=1e-5,
    )


def test_from_pretrained_picks_the_family() -> None:
    da3_path = shared_path("golden", "da3", "weights.safetensors")
    da3 = TorchBackend.from_pretrained(da3_path)
    assert (da3.info.family, da3.info.model) == ("da3", "da3-custom")
    assert da3.info.weights_fingerprint == load_da3(da3_path).fingerprint
    assert da3.info.layout == CacheLayout((5, 7, 9, 11), 2, 64)
    pi3 = TorchBackend.from_pretrained(shared_path("golden", "pi3", "weights.safetensors"))
    assert pi3.info.family == "pi3" and pi3.info.fingerprint != da3.info.fingerprint
    # a cache from the other family is refused
    frames = np.zeros((2, 112, 154, 3), dtype=np.uint8)
    with pytest.raises(BackendMismatchError, match="layout"):
        da3.track(frames[0], pi3.map(frames).cache)

"""TorchBackend: the Backend contract on a small random Pi3 (and the golden checkpoint); the tests
both families share are in ``test_torch_backend_families.py``."""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import pytest
import torch

from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.cache.kv_cache import CacheLayout, KVCache
from kvtracker_sdk.errors import (
    BackendMismatchError,
    ImageDtypeError,
    ImageShapeError,
    MaskError,
    ResolutionChangedError,
    StateError,
)
from kvtracker_sdk.models.pi3 import Pi3, load_pi3
from kvtracker_sdk.types import HeadSet
from tests.helpers import shared_path
from tests.models.pi3.factories import random_pi3

H, W = 28, 42  # a 2x3 patch grid: 5 + 6 = 11 tokens per frame


@pytest.fixture(scope="module")
def model() -> Pi3:
    return random_pi3(seed=7)


@pytest.fixture(scope="module")
def backend(model: Pi3) -> TorchBackend:
    return TorchBackend(copy.deepcopy(model), model_name="tiny")


@pytest.fixture(scope="module")
def images() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, size=(4, H, W, 3), dtype=np.uint8)


def test_map_shapes_and_dtypes(backend: TorchBackend, images: np.ndarray) -> None:
    result = backend.map(images[:3])
    assert result.poses.shape == (3, 4, 4) and result.poses.dtype == np.float64
    assert result.confidence.shape == (3, H, W) and result.confidence.dtype == np.float32
    assert result.confidence.min() >= 0.0 and result.confidence.max() <= 1.0
    assert result.local_points.shape == (3, H, W, 3) and result.local_points.dtype == np.float32
    assert (result.local_points[..., 2] > 0).all()
    assert not result.poses.flags.writeable
    np.testing.assert_allclose(np.linalg.det(result.poses[:, :3, :3]), 1.0, atol=1e-5)
    cache = result.cache
    assert (cache.num_keyframes, cache.tokens_per_frame, cache.dtype) == (3, 11, torch.float32)
    assert cache.layout == backend.info.layout
    assert result.timings_ms["map"] > 0


def test_map_equals_model_forward_map(
    backend: TorchBackend, model: Pi3, images: np.ndarray
) -> None:
    frames = torch.from_numpy(images[:3]).permute(0, 3, 1, 2).float().unsqueeze(0) / 255.0
    with torch.no_grad():
        reference = model.forward_map(frames)
    result = backend.map(images[:3])
    np.testing.assert_allclose(
        result.poses, reference.output.camera_poses[0].double().numpy(), atol=1e-6
    )
    torch.testing.assert_close(result.cache.keys(1), reference.keys[1], atol=1e-6, rtol=0)


def test_track_batch_equals_single_tracks(backend: TorchBackend, images: np.ndarray) -> None:
    cache = backend.map(images[:2]).cache
    batch = backend.track_batch(images[2:], cache, heads=HeadSet.ALL)
    assert len(batch) == 2
    for index, result in enumerate(batch):
        single = backend.track(images[2 + index], cache, heads=HeadSet.ALL)
        np.testing.assert_allclose(result.pose, single.pose, atol=1e-5)
        np.testing.assert_allclose(result.local_points, single.local_points, atol=1e-4, rtol=1e-4)  # type: ignore[arg-type]


def test_track_holds_the_cache_lock(
    backend: TorchBackend, images: np.ndarray, monkeypatch: pytest.MonkeyPatch
) -> None:
    cache = backend.map(images[:2]).cache
    seen: list[bool] = []

    class RecordingLock:
        held = False

        def __enter__(self) -> None:
            RecordingLock.held = True

        def __exit__(self, *_: Any) -> None:
            RecordingLock.held = False

    cache.lock = RecordingLock()  # type: ignore[assignment]
    model = backend._live_model()
    original = model.forward_track
    monkeypatch.setattr(
        model, "forward_track", lambda *a, **k: seen.append(RecordingLock.held) or original(*a, **k)
    )
    backend.track(images[2], cache)
    assert seen == [True] and not RecordingLock.held


def test_typed_errors(backend: TorchBackend, model: Pi3, images: np.ndarray) -> None:
    cache = backend.map(images[:2]).cache
    with pytest.raises(ImageDtypeError):
        backend.map(images.astype(np.float32))
    with pytest.raises(ImageShapeError):
        backend.map(images[0])
    with pytest.raises(ImageShapeError, match="multiple of 14"):
        backend.map(images[:, :, :40])
    with pytest.raises(MaskError):
        backend.map(images[:2], masks=np.ones((2, H, W), dtype=np.uint8))
    with pytest.raises(ImageShapeError):
        backend.track(images[:2], cache)
    with pytest.raises(ResolutionChangedError):
        backend.track(np.zeros((H, 56, 3), dtype=np.uint8), cache)
    with pytest.raises(BackendMismatchError, match="layout"):
        backend.track(images[2], KVCache(CacheLayout((1, 3, 5), 2, 16), 11))
    with pytest.raises(BackendMismatchError, match=r"cache\.to"):
        backend.track(images[2], cache.to(dtype=torch.bfloat16))
    closed = TorchBackend(copy.deepcopy(model))
    closed.close()
    closed.close()  # idempotent
    with pytest.raises(StateError):
        closed.track(images[2], cache)


def test_from_pretrained_golden_checkpoint() -> None:
    path = shared_path("golden", "pi3", "weights.safetensors")
    backend = TorchBackend.from_pretrained(path)
    assert backend.info.model == "pi3-custom"
    assert backend.info.weights_fingerprint == load_pi3(path).fingerprint
    assert backend.info.layout == CacheLayout((1, 3, 5, 7), 2, 32)

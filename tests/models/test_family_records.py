"""The family records (``models/<family>/family.py``): both answer in the SDK's conventions."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.errors import ModelError
from kvtracker_sdk.models.da3 import load_da3
from kvtracker_sdk.models.da3.family import DA3Family
from kvtracker_sdk.models.family import FrameOutputs, ModelFamily
from kvtracker_sdk.models.pi3 import load_pi3
from kvtracker_sdk.models.pi3.family import Pi3Family
from kvtracker_sdk.models.registry import FAMILIES, family_of
from kvtracker_sdk.types import HeadSet
from tests.helpers import shared_path


def _cache(
    family: ModelFamily, model: torch.nn.Module, frames: torch.Tensor
) -> tuple[KVCache, FrameOutputs]:
    mapped = family.map(model, frames)
    cache = KVCache.from_layers(
        mapped.keys,
        mapped.values,
        layout=family.cache_layout(model),
        tokens_per_frame=mapped.tokens_per_frame,
        keyframe_ids=range(frames.shape[0]),
    )
    return cache, mapped.frames


@torch.no_grad()
def test_da3_record_converts_conventions() -> None:
    model = load_da3(shared_path("golden", "da3", "weights.safetensors")).model
    family = family_of(model)
    assert isinstance(family, DA3Family) and family.name == "da3"
    assert family.extra_tokens_per_frame(model) == 1
    assert family.cache_layout(model).block_indices == (5, 7, 9, 11)
    imgs = load_file(shared_path("golden", "da3", "inputs.safetensors"))["imgs_01"][0]
    cache, frames = _cache(family, model, imgs[:3])
    assert frames.poses.dtype == np.float64 and frames.poses.shape == (3, 4, 4)
    expected = load_file(shared_path("golden", "da3", "outputs_query.safetensors"))
    # T_world_cam is the inverse of DA3's world-to-camera extrinsics
    world_to_cam = expected["keyframes.extrinsics"][0].double().numpy()
    products = frames.poses[:, :3, :3] @ world_to_cam[:, :3, :3]
    np.testing.assert_allclose(products, np.broadcast_to(np.eye(3), (3, 3, 3)), atol=1e-5)
    assert frames.confidence is not None and frames.local_points is not None
    assert frames.confidence.min() >= 0.0 and frames.confidence.max() < 1.0
    np.testing.assert_allclose(
        frames.local_points[..., 2], expected["keyframes.depth"][0].numpy(), rtol=1e-4
    )
    camera = family.track(model, imgs[3:4], cache, HeadSet.CAMERA)
    assert camera.confidence is None and camera.local_points is None
    full = family.track(model, imgs[3:4], cache, HeadSet.ALL)
    np.testing.assert_array_equal(camera.poses, full.poses)
    assert full.local_points is not None and full.local_points.shape == (1, 112, 154, 3)
    confidence = family.track(model, imgs[3:4], cache, HeadSet.CONFIDENCE)
    assert confidence.confidence is not None and confidence.local_points is None


@torch.no_grad()
def test_pi3_record_keeps_its_outputs() -> None:
    model = load_pi3(shared_path("golden", "pi3", "weights.safetensors")).model
    family = family_of(model)
    assert isinstance(family, Pi3Family) and family.extra_tokens_per_frame(model) == 5
    imgs = load_file(shared_path("golden", "pi3", "case1", "inputs.safetensors"))["imgs"][0]
    cache, frames = _cache(family, model, imgs[:3])
    expected = load_file(shared_path("golden", "pi3", "case1", "outputs_query.safetensors"))
    np.testing.assert_allclose(
        frames.poses, expected["keyframes.camera_poses"][0].numpy(), atol=1e-5
    )
    tracked = family.track(model, imgs[3:4], cache, HeadSet.CONFIDENCE)
    np.testing.assert_allclose(
        tracked.poses, expected["query.camera_poses"][:, 0].numpy(), atol=1e-5
    )
    assert tracked.confidence is not None and tracked.local_points is None


def test_other_networks_are_rejected() -> None:
    with pytest.raises(ModelError, match="neither a Pi3 nor a DepthAnything3"):
        family_of(torch.nn.Linear(2, 2))


def test_the_registry_lists_each_family_once_under_its_name() -> None:
    assert list(FAMILIES) == ["pi3", "da3"]
    assert all(name == family.name for name, family in FAMILIES.items())
    assert len({family.model_type for family in FAMILIES.values()}) == len(FAMILIES)


def test_every_family_has_a_preprocessing() -> None:
    """The one thing a family provides outside its folder (layer 0): a missing line in
    ``preprocess.FAMILY_PREPROCESSING`` would only show when a tracker prepares a frame."""
    from kvtracker_sdk.preprocess import for_family

    for name in FAMILIES:
        assert for_family(name).name  # ConfigError when the family has none

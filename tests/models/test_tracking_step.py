"""The tracking step both families share (``models/layers/alternating.py``): a cache the model
refuses is left exactly as it was, and several queries get a mask of their own rows only."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.errors import CacheError
from kvtracker_sdk.models.layers.alternating import CacheTrackingStep
from kvtracker_sdk.models.registry import family_of
from kvtracker_sdk.types import HeadSet
from tests.models.da3.factories import random_da3
from tests.models.pi3.factories import random_pi3

FACTORIES = {"pi3": random_pi3, "da3": random_da3}
H, W = 28, 42  # a 2x3 patch grid


def _full_cache(model: nn.Module, frames: torch.Tensor) -> KVCache:
    """A cache of the frames' keyframes with one frame of spare capacity (the least
    ``from_layers`` keeps): tracking two frames must grow it."""
    mapped = family_of(model).map(model, frames)
    cache = KVCache.from_layers(
        mapped.keys,
        mapped.values,
        layout=family_of(model).cache_layout(model),
        tokens_per_frame=mapped.tokens_per_frame,
        keyframe_ids=range(frames.shape[0]),
        spare_frames=0,
    )
    return cache


@pytest.mark.parametrize("family", sorted(FACTORIES))
@torch.no_grad()
def test_a_refused_cache_is_not_grown(family: str) -> None:
    model = FACTORIES[family](seed=0)
    frames = torch.rand(4, 3, H, W, generator=torch.Generator().manual_seed(1))
    cache = _full_cache(model, frames[:2]).to(dtype=torch.bfloat16)  # the model computes in fp32
    capacity, storage, keys = cache.capacity, cache.buffers(0)[0].data_ptr(), cache.keys(0).clone()
    with pytest.raises(CacheError, match="bfloat16"):
        model.forward_track(frames[2:], cache, heads=HeadSet.CAMERA)  # type: ignore[operator]
    assert cache.capacity == capacity  # checked before it grew: same buffers, same content
    assert cache.buffers(0)[0].data_ptr() == storage and torch.equal(cache.keys(0), keys)


@torch.no_grad()
def test_several_queries_get_their_rows_of_the_mask_only() -> None:
    model = random_pi3(seed=0)
    frames = torch.rand(2, 3, H, W, generator=torch.Generator().manual_seed(1))
    cache = _full_cache(model, frames)
    layout = family_of(model).cache_layout(model)
    tokens = cache.tokens_per_frame
    step = CacheTrackingStep(
        cache, layout, frames=3, tokens_per_frame=tokens, rope=None,
        dtype=torch.float32, device=torch.device("cpu"),
    )  # fmt: skip
    mask = step.masks[cache.length]
    assert mask is not None and mask.shape == (3 * tokens, cache.length + 3 * tokens)
    assert cache.capacity >= cache.length + 3 * tokens  # grown for the queries' scratch
    first_query = mask[:tokens]  # sees every cached token and its own frame only
    assert first_query[:, : cache.length].all() and first_query[:, cache.length :][:, :tokens].all()
    assert not first_query[:, cache.length + tokens :].any()

"""The kernels of the tracking step's attention over the cache (``cached_attention.py``)."""

from __future__ import annotations

import copy

import pytest
import torch
import torch.nn.functional as F

from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.models.layers.attention import keyframe_query_mask
from kvtracker_sdk.models.layers.cached_attention import cached_attention, use_cached_kernel
from kvtracker_sdk.types import HeadSet
from tests.models.pi3.factories import random_pi3


def _inputs(dtype: torch.dtype, queries: int = 150, keys: int = 420) -> tuple[torch.Tensor, ...]:
    gen = torch.Generator().manual_seed(5)
    q = torch.randn(1, 3, queries, 16, generator=gen) * 3  # scores spread over several units
    k, v = torch.randn(2, 1, 3, keys, 16, generator=gen)
    return q.to(dtype), k.to(dtype), v.to(dtype)


@pytest.mark.parametrize("masked", [False, True])
def test_products_equal_sdpa_in_fp32(masked: bool) -> None:
    q, k, v = _inputs(torch.float32)
    # 150 queries = 2 frames of 75 over 270 cached tokens: more than one 64-query chunk
    mask = keyframe_query_mask(270, 2, 75, queries_only=True) if masked else None
    expected = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
    got = cached_attention(q, k, v, mask, kernel="products")
    torch.testing.assert_close(got, expected, atol=2e-6, rtol=1e-5)


def test_products_in_bf16_stay_near_float64() -> None:
    q, k, v = _inputs(torch.bfloat16)
    reference = F.scaled_dot_product_attention(q.double(), k.double(), v.double())
    error = (cached_attention(q, k, v, kernel="products").double() - reference).abs().max()
    assert error < 0.05  # bf16 scores and probabilities; SDPA's fp32 scores give ~0.01 here


def test_unknown_kernels_are_config_errors() -> None:
    q, k, v = _inputs(torch.float32, 4, 8)
    with pytest.raises(ConfigError, match="flash2"):
        cached_attention(q, k, v, kernel="flash2")
    with pytest.raises(ConfigError):
        use_cached_kernel(random_pi3(seed=2), "flash2")


def test_a_model_tracks_alike_with_either_kernel() -> None:
    from kvtracker_sdk.cache.kv_cache import KVCache
    from kvtracker_sdk.models.registry import family_of

    model = random_pi3(seed=2).eval()
    products = use_cached_kernel(copy.deepcopy(model), "products")
    kernels = {m.cached_kernel for m in products.modules() if hasattr(m, "cached_kernel")}
    assert kernels == {"products"}
    frames = torch.rand(1, 3, 3, 28, 42, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        mapped = model.forward_map(frames[:, :2], heads=HeadSet.CAMERA)
        layout = family_of(model).cache_layout(model)
        cache = KVCache.from_layers(mapped.keys, mapped.values, layout=layout,
                                    tokens_per_frame=mapped.tokens_per_frame, keyframe_ids=[0, 1])
        expected = model.forward_track(frames[0, 2:], cache).camera_poses
        got = products.forward_track(frames[0, 2:], cache).camera_poses
    torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-5)

"""KVCache: preallocated buffers, append without re-copying, drop, clone, equality."""

from __future__ import annotations

import pytest
import torch

from kvtracker_sdk.cache import CacheLayout, KVCache
from kvtracker_sdk.errors import CacheError

LAYOUT = CacheLayout(block_indices=(1, 3, 5), num_heads=2, head_dim=8)
T = 7  # tokens per frame


def frame_kv(seed: int, dtype: torch.dtype = torch.float32) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    g = torch.Generator().manual_seed(seed)
    shape = (1, LAYOUT.num_heads, T, LAYOUT.head_dim)
    keys = [torch.randn(shape, generator=g).to(dtype) for _ in range(LAYOUT.num_layers)]
    values = [torch.randn(shape, generator=g).to(dtype) for _ in range(LAYOUT.num_layers)]
    return keys, values


def cache_of(n: int, dtype: torch.dtype = torch.float32) -> KVCache:
    frames = [frame_kv(i, dtype) for i in range(n)]
    keys = [torch.cat([f[0][layer] for f in frames], dim=2) for layer in range(LAYOUT.num_layers)]
    values = [torch.cat([f[1][layer] for f in frames], dim=2) for layer in range(LAYOUT.num_layers)]
    return KVCache.from_layers(keys, values, layout=LAYOUT, tokens_per_frame=T, keyframe_ids=list(range(n)))


def test_from_layers_exposes_exact_views_and_bytes() -> None:
    cache = cache_of(3)
    assert cache.num_keyframes == 3 and cache.length == 3 * T
    assert cache.capacity >= cache.length + T  # scratch room for one query frame
    k0, _ = frame_kv(0)
    assert torch.equal(cache.keys(1)[:, :, :T], k0[1])
    assert cache.nbytes == 2 * LAYOUT.num_layers * LAYOUT.num_heads * 3 * T * LAYOUT.head_dim * 4
    assert cache.bytes_per_keyframe() * 3 == cache.nbytes


def test_append_equals_building_from_all_frames_and_keeps_storage() -> None:
    cache = cache_of(2)
    storage = cache.buffers(0)[0].data_ptr()
    keys, values = frame_kv(2)
    cache.append_keyframe(keys, values, keyframe_id=2)
    assert cache.equals(cache_of(3))
    # room was preallocated: appending one frame must not reallocate the buffer
    assert cache.buffers(0)[0].data_ptr() == storage


def test_append_grows_past_capacity_and_keeps_content() -> None:
    cache = cache_of(1)
    for i in range(1, 9):
        cache.append_keyframe(*frame_kv(i), keyframe_id=i)
    assert cache.equals(cache_of(9))


def test_drop_keyframes_compacts_in_order() -> None:
    cache = cache_of(4)
    cache.drop_keyframes([1])
    expected = cache_of(4)
    assert cache.keyframe_ids == (0, 2, 3)
    for layer in range(LAYOUT.num_layers):
        kept = torch.cat([expected.keys(layer)[:, :, i * T : (i + 1) * T] for i in (0, 2, 3)], dim=2)
        assert torch.equal(cache.keys(layer), kept)
    with pytest.raises(CacheError):
        cache.drop_keyframes([7])


def test_clone_is_independent_and_equal() -> None:
    cache = cache_of(2)
    twin = cache.clone()
    assert twin.equals(cache)
    twin.buffers(0)[0][0, 0, 0, 0] += 1.0
    assert not twin.equals(cache)


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_dtype_conversion_and_equality_checks_dtype(dtype: torch.dtype) -> None:
    cache = cache_of(2)
    converted = cache.to(dtype=dtype)
    assert converted.dtype == dtype
    assert converted.equals(cache) == (dtype == torch.float32)


def test_bad_shapes_and_duplicates_are_typed_errors() -> None:
    cache = cache_of(2)
    keys, values = frame_kv(5)
    with pytest.raises(CacheError):
        cache.append_keyframe(keys, values, keyframe_id=0)
    with pytest.raises(CacheError):
        cache.append_keyframe(keys[:1], values[:1], keyframe_id=9)
    with pytest.raises(CacheError):
        cache.append_keyframe([k[:, :, :3] for k in keys], values, keyframe_id=9)
    with pytest.raises(CacheError):
        KVCache.from_layers(keys, values, layout=LAYOUT, tokens_per_frame=T, keyframe_ids=[0, 1])
    assert cache.equals(cache_of(2))  # failed edits left it untouched

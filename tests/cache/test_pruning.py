"""Pruned caches: per-layer lengths in ``KVCache``, the budgeted redundancy pruning of
``cache/pruning.py``, and a tracking step that reads each layer's own length."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from kvtracker_sdk.cache import KVCache
from kvtracker_sdk.cache.pruning import object_token_mask, prune_cache, redundancy_scores
from kvtracker_sdk.errors import CacheError
from kvtracker_sdk.models.layers.alternating import PastInputsStep
from kvtracker_sdk.models.registry import family_of
from kvtracker_sdk.types import HeadSet
from tests.cache.test_kv_cache import LAYOUT, T, cache_of, frame_kv
from tests.models.pi3.factories import random_pi3


def test_kept_tokens_shrink_each_layer_and_bytes() -> None:
    cache, full = cache_of(3), cache_of(3)
    kept = [torch.arange(0, 3 * T, 2), torch.arange(3 * T), torch.tensor([0, 5, 20])]
    cache.keep_tokens(kept)
    assert [cache.layer_length(i) for i in range(3)] == [11, 21, 3] and cache.length == 21
    for i, index in enumerate(kept):
        assert torch.equal(cache.keys(i), full.keys(i)[:, :, index])
        assert torch.equal(cache.values(i), full.values(i)[:, :, index])
        assert torch.equal(cache.kept_tokens(i), index)
    per_token = 2 * LAYOUT.num_heads * LAYOUT.head_dim * 4
    assert cache.nbytes == (11 + 21 + 3) * per_token
    assert cache.clone().equals(cache) and not cache.equals(full)
    with pytest.raises(CacheError, match="increase"):
        cache.keep_tokens([torch.tensor([1, 0])] * 3)


def test_a_pruned_cache_drops_and_appends_keyframes_by_their_kept_tokens() -> None:
    cache = cache_of(3)
    kept = [torch.tensor([0, 3, T + 1, 2 * T + 6])] * 3
    cache.keep_tokens(kept)
    cache.drop_keyframes([1])  # keyframe 1's token T + 1 goes; keyframe 2's move down by T
    assert torch.equal(cache.kept_tokens(0), torch.tensor([0, 3, T + 6]))
    expected = cache_of(3)
    expected.drop_keyframes([1])
    assert torch.equal(cache.keys(2), expected.keys(2)[:, :, [0, 3, T + 6]])
    keys, values = frame_kv(7)
    cache.append_keyframe(keys, values, keyframe_id=7)  # a new keyframe keeps all its tokens
    assert cache.layer_length(1) == 3 + T and cache.keyframe_ids == (0, 2, 7)
    assert torch.equal(cache.keys(1)[:, :, 3:], keys[1])
    assert torch.equal(cache.kept_tokens(1)[3:], torch.arange(2 * T, 3 * T))


def test_adopting_the_scratch_appends_the_last_pass_frame() -> None:
    cache = cache_of(2)
    cache.keep_tokens([torch.arange(0, 2 * T, 2)] * 3)
    keys, values = frame_kv(5)
    for i in range(3):  # what a one-frame tracking pass leaves after each layer's length
        key_buffer, value_buffer = cache.buffers(i)
        key_buffer[:, :, T : 2 * T].copy_(keys[i])
        value_buffer[:, :, T : 2 * T].copy_(values[i])
    cache.adopt_scratch(5)
    assert cache.keyframe_ids == (0, 1, 5) and cache.layer_length(0) == 2 * T
    assert torch.equal(cache.keys(2)[:, :, T:], keys[2])
    assert cache.capacity >= cache.length + T  # room for the next pass


def test_prune_cache_keeps_the_budget_protected_tokens_and_drops_the_most_redundant() -> None:
    cache = cache_of(4)
    extra = 2
    # make token 3 of keyframe 2 (index 2T+3) a copy of the layer's mean key in every layer:
    # the most redundant token there is
    for i in range(LAYOUT.num_layers):
        keys = cache.buffers(i)[0]
        keys[:, :, 2 * T + 3] = keys[:, :, : 4 * T].mean(dim=2) * 10
    prune_cache(cache, keep_ratio=0.5, extra_tokens_per_frame=extra)
    budget = int(np.ceil(0.5 * 4 * T))
    for i in range(LAYOUT.num_layers):
        kept = set(cache.kept_tokens(i).tolist())
        assert cache.layer_length(i) == budget
        assert set(range(T)) <= kept  # keyframe 0
        assert {f * T + e for f in range(4) for e in range(extra)} <= kept  # registers
        assert 2 * T + 3 not in kept
    with pytest.raises(CacheError, match="already pruned"):
        prune_cache(cache, keep_ratio=0.5, extra_tokens_per_frame=extra)


def test_redundancy_is_cosine_similarity_to_the_mean_key() -> None:
    keys = torch.tensor([[[[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]]])  # 1 head, 3 tokens
    scores = redundancy_scores(keys)
    assert scores.argmax() == 2 and torch.isclose(scores[2], torch.tensor(1.0))


def test_object_mode_keeps_the_dilated_object_patches_and_the_extra_tokens() -> None:
    mask = np.zeros((28, 56), dtype=bool)  # a 2x4 patch grid at patch 14
    mask[3, 2] = True  # one pixel in patch (0, 0)
    keep = object_token_mask([mask, None], patch_size=14, extra_tokens_per_frame=1)
    first = keep[:9]
    assert first[0] and first[1:].tolist() == [True, True, False, False, True, True, False, False]
    assert keep[9:].all()  # no mask: the whole frame
    tight = object_token_mask([mask], patch_size=14, extra_tokens_per_frame=1, dilation_patches=0)
    assert tight.tolist() == [True, True] + [False] * 7


@torch.no_grad()
def test_tracking_reads_each_layers_own_length() -> None:
    """Layers pruned to different lengths: the step equals attending over each layer's kept K/V
    given as past inputs (the exported graphs' step), to 1e-5."""
    model = random_pi3(seed=0)
    frames = torch.rand(3, 3, 28, 42, generator=torch.Generator().manual_seed(1))
    family = family_of(model)
    mapped = family.map(model, frames[:2])
    cache = KVCache.from_layers(
        mapped.keys, mapped.values, layout=family.cache_layout(model),
        tokens_per_frame=mapped.tokens_per_frame, keyframe_ids=[0, 1],
    )  # fmt: skip
    full = 2 * cache.tokens_per_frame
    g = torch.Generator().manual_seed(2)
    cache.keep_tokens(
        [torch.sort(torch.randperm(full, generator=g)[: full - 3 * i]).values
         for i in range(cache.layout.num_layers)]
    )  # fmt: skip
    assert len({cache.layer_length(i) for i in range(cache.layout.num_layers)}) > 1
    reference = [
        (cache.keys(i).clone(), cache.values(i).clone()) for i in range(cache.layout.num_layers)
    ]
    tracked = model.forward_track(frames[2:], cache, heads=HeadSet.CAMERA)

    def per_layer_past(ordinal: int, block: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
        key, value = reference[ordinal]
        return PastInputsStep((key, value), torch.tensor(key.shape[2]), rope)(0, block, x)  # type: ignore[arg-type]

    tokens, rope = model._encode(frames[2:].unsqueeze(0))
    hidden = model.decoder.run(tokens, rope, per_layer_past)
    expected = model._heads(hidden.transpose(0, 1), (28, 42), HeadSet.CAMERA)
    assert torch.allclose(tracked.camera_poses, expected.camera_poses, atol=1e-5)


def test_object_mode_drops_tokens_off_the_object_also_in_keyframe_0() -> None:
    cache = cache_of(2)
    allowed = torch.zeros(2 * T, dtype=torch.bool)
    allowed[[0, 4, T + 5]] = True  # token 0 is an extra token anyway
    prune_cache(cache, keep_ratio=1.0, extra_tokens_per_frame=2, allowed=allowed)
    assert cache.kept_tokens(0).tolist() == [0, 1, 4, T, T + 1, T + 5]


def test_uniform_pruning_spreads_the_kept_patches_evenly() -> None:
    cache = cache_of(4)  # 4 frames of T = 7 tokens, 2 extra each: 5 patches per frame
    prune_cache(cache, keep_ratio=0.6, extra_tokens_per_frame=2, score="uniform")
    kept = cache.kept_tokens(0)
    per_frame = torch.bincount(kept // T, minlength=4).tolist()
    assert per_frame[0] == T and max(per_frame[1:]) - min(per_frame[1:]) <= 1  # keyframe 0 whole
    assert all(torch.equal(cache.kept_tokens(i), kept) for i in range(3))  # same in every layer
    with pytest.raises(CacheError, match="unknown pruning score"):
        prune_cache(cache_of(2), keep_ratio=0.5, extra_tokens_per_frame=2, score="attention")


def test_a_quantised_cache_has_no_scratch_to_adopt() -> None:
    cache = cache_of(2).to(storage="int8")
    with pytest.raises(CacheError, match="quantised"):
        cache.adopt_scratch(5)
    pruned = cache_of(3)
    pruned.keep_tokens([torch.arange(0, 3 * T, 3)] * 3)
    quantized = pruned.to(storage="int8")  # pruning survives quantisation
    assert quantized.pruned and torch.equal(quantized.kept_tokens(1), pruned.kept_tokens(1))
    assert torch.allclose(quantized.keys(2), pruned.keys(2), atol=0.05)

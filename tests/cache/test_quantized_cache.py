"""Quantised K/V (int8, fp8 e4m3): the math, and a ``KVCache`` that keeps them at rest.

Tolerances: int8 with a scale per token and head rounds each value to within half a step,
step = absmax / 127 of its token in its head, times the scale's rounding up (float8 e5m2: at most
x1.25), so |x' - x| <= 0.5 * 1.25 * absmax / 127 (+ float32 rounding); fp8 e4m3 keeps 3 mantissa
bits: relative error <= 2**-4 of each value above the subnormal range.
"""

from __future__ import annotations

import pytest
import torch

from kvtracker_sdk.cache import CacheLayout, KVCache
from kvtracker_sdk.cache.quantization import (
    QUANTIZED_STORAGES,
    dequantize,
    quantize,
    round_up,
    storage_name,
)
from kvtracker_sdk.errors import CacheError

LAYOUT = CacheLayout((1, 3), num_heads=2, head_dim=16)
TOKENS = 5


def _layers(keyframes: int, seed: int = 0) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    generator = torch.Generator().manual_seed(seed)
    shape = (1, LAYOUT.num_heads, keyframes * TOKENS, LAYOUT.head_dim)
    # heads and tokens of very different magnitudes: a shared scale would lose the small ones
    magnitude = torch.logspace(-2, 2, keyframes * TOKENS).view(1, 1, -1, 1)
    keys = [torch.randn(shape, generator=generator) * magnitude for _ in LAYOUT.block_indices]
    values = [torch.randn(shape, generator=generator) * magnitude for _ in LAYOUT.block_indices]
    return keys, values


def test_int8_error_is_within_half_a_step_per_token_and_head() -> None:
    x = _layers(3)[0][0]
    data, scale = quantize(x, QUANTIZED_STORAGES["int8"], "token_head")
    assert data.dtype == torch.int8 and scale.dtype == torch.float8_e5m2
    assert scale.shape == (1, LAYOUT.num_heads, 3 * TOKENS, 1)
    absmax = x.abs().amax(-1, keepdim=True)
    assert torch.all(scale.float() >= absmax / 127)  # rounded up: nothing is clipped
    error = (dequantize(data, scale, torch.float32) - x).abs()
    assert torch.all(error <= 0.5 * 1.25 * absmax / 127 * (1 + 1e-5))
    assert x.equal(_layers(3)[0][0])  # the input is not scaled in place


def test_fp8_keeps_three_mantissa_bits() -> None:
    x = _layers(3)[0][0]
    data, scale = quantize(x, QUANTIZED_STORAGES["float8_e4m3fn"], "token_head")
    assert data.dtype == torch.float8_e4m3fn
    restored = dequantize(data, scale, torch.float32)
    normal = (x / scale.float()).abs() >= 2**-6  # e4m3's smallest normal
    assert torch.all(((restored - x).abs() <= 2**-4 * x.abs())[normal])


def test_round_up_never_goes_below_and_saturates() -> None:
    x = torch.tensor([1e-9, 0.3, 1.0, 1.1, 7e4])
    up = round_up(x, torch.float8_e5m2).float()
    assert torch.all(up[1:4] >= x[1:4]) and torch.all(up[1:4] <= 1.25 * x[1:4])
    assert up[0] == torch.finfo(torch.float8_e5m2).tiny and up[4] == 57344.0


@pytest.mark.parametrize("storage", ["int8", "fp8"])
def test_a_quantised_cache_is_smaller_and_reads_back_close(storage: str) -> None:
    keys, values = _layers(3)
    dense = KVCache.from_layers(keys, values, layout=LAYOUT, tokens_per_frame=TOKENS,
                                keyframe_ids=[4, 5, 6])  # fmt: skip
    cache = dense.to(storage=storage)
    assert cache.storage == storage_name(storage) and cache.quantized
    assert cache.dtype == torch.float32 and not dense.quantized
    # per token and head: 16 data bytes + 1 scale byte vs 32 bytes in bf16
    assert dense.to(dtype=torch.bfloat16).nbytes / cache.nbytes == pytest.approx(32 / 17)
    for layer in range(LAYOUT.num_layers):
        for restored, x in ((cache.keys(layer), keys[layer]), (cache.values(layer), values[layer])):
            absmax = x.abs().amax(-1, keepdim=True)  # of each token in each head
            if storage == "int8":  # half a step, the scale rounded up by at most x1.25
                bound = 0.5 * 1.25 * absmax / 127 * (1 + 1e-5)
            else:  # 3 mantissa bits; subnormal steps of 2**-9 * scale below 2**-6 * scale
                bound = 2**-4 * x.abs() + 2**-10 * 1.25 * absmax / 448
            assert torch.all((restored - x).abs() <= bound)


def test_buffers_dequantise_one_layer_into_one_shared_work_pair() -> None:
    keys, values = _layers(3)
    cache = KVCache.from_layers(keys, values, layout=LAYOUT, tokens_per_frame=TOKENS,
                                keyframe_ids=[0, 1, 2], storage="int8")  # fmt: skip
    first = cache.buffers(0)
    first_keys = first[0][:, :, : cache.length].clone()
    second = cache.buffers(1)
    assert second[0] is first[0] and second[1] is first[1]  # one pair, not one per layer
    assert second[0].shape[2] == cache.capacity > cache.length  # scratch after the tokens
    assert torch.equal(first_keys, cache.keys(0))
    assert torch.equal(second[0][:, :, : cache.length], cache.keys(1))
    assert cache.peek_buffers(1)[0] is first[0]
    with pytest.raises(IndexError):
        cache.peek_buffers(LAYOUT.num_layers)


def test_editing_a_quantised_cache_touches_only_the_tokens_edited() -> None:
    keys, values = _layers(4)
    head = [k[:, :, : 3 * TOKENS] for k in keys], [v[:, :, : 3 * TOKENS] for v in values]
    cache = KVCache.from_layers(*head, layout=LAYOUT, tokens_per_frame=TOKENS,
                                keyframe_ids=[0, 1, 2], storage="int8")  # fmt: skip
    before = cache.clone()
    cache.append_keyframe([k[:, :, 3 * TOKENS :] for k in keys],
                          [v[:, :, 3 * TOKENS :] for v in values], keyframe_id=3)  # fmt: skip
    whole = KVCache.from_layers(keys, values, layout=LAYOUT, tokens_per_frame=TOKENS,
                                keyframe_ids=[0, 1, 2, 3], storage="int8")  # fmt: skip
    assert cache.equals(whole)  # per-token scales: appending equals quantising all at once
    cache.drop_keyframes([3])
    assert cache.equals(before)
    cache.drop_keyframes([1])
    for name, part in cache.stored_parts(0).items():
        kept = torch.cat((before.stored_parts(0)[name][:, :, :TOKENS],
                          before.stored_parts(0)[name][:, :, 2 * TOKENS :]), dim=2)  # fmt: skip
        assert torch.equal(part.view(torch.uint8), kept.view(torch.uint8)), name


def test_a_dtype_change_keeps_the_quantised_data_bit_for_bit() -> None:
    cache = KVCache.from_layers(*_layers(2), layout=LAYOUT, tokens_per_frame=TOKENS,
                                keyframe_ids=[0, 1], storage="int8")  # fmt: skip
    bf16 = cache.to(dtype=torch.bfloat16)
    assert bf16.storage == "int8" and bf16.dtype == torch.bfloat16
    assert bf16.buffers(0)[0].dtype == torch.bfloat16
    assert bf16.to(dtype=torch.float32).equals(cache)
    dense = cache.to(storage="float32")
    assert not dense.quantized and torch.equal(dense.keys(1), cache.keys(1))
    with pytest.raises(CacheError):
        cache.to(dtype=torch.bfloat16, storage="float32")
    with pytest.raises(CacheError):
        cache.to(storage="int4")

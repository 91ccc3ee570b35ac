"""The mixed-precision helpers (``models/layers/precision.py``) and the K/V dtype of attention."""

from __future__ import annotations

import torch
from torch import nn

from kvtracker_sdk.models.layers.attention import Attention
from kvtracker_sdk.models.layers.block import Block
from kvtracker_sdk.models.layers.patch_embed import PatchEmbed
from kvtracker_sdk.models.layers.precision import (
    cast_matmul_weights,
    matmul_dtype,
    trunk_autocast,
)


def test_cast_matmul_weights_casts_linear_and_conv_only() -> None:
    model = nn.Sequential(PatchEmbed(14, 8), Block(8, 2, qk_norm=True, layerscale_init=0.1))
    cast_matmul_weights(model, torch.bfloat16)
    casts = {name: param.dtype for name, param in model.named_parameters()}
    matmul = {name for name in casts if any(k in name for k in ("proj.", "qkv.", "fc1.", "fc2."))}
    assert matmul and all(casts[name] == torch.bfloat16 for name in matmul)
    assert {casts[name] for name in casts.keys() - matmul} == {torch.float32}  # norms, gammas


def test_trunk_autocast_keeps_a_callers_autocast_in_fp32() -> None:
    x = torch.ones(2, 2)
    with trunk_autocast(torch.bfloat16, x.device):
        assert matmul_dtype(x) == torch.bfloat16 and (x @ x).dtype == torch.bfloat16
    with trunk_autocast(torch.float32, x.device):
        assert matmul_dtype(x) == torch.float32 and (x @ x).dtype == torch.float32
    with torch.autocast("cpu", dtype=torch.bfloat16), trunk_autocast(torch.float32, x.device):
        assert matmul_dtype(x) == torch.bfloat16  # not switched off
    assert matmul_dtype(x.to(torch.bfloat16)) == torch.bfloat16


class _Fp32Norm(nn.LayerNorm):
    """A qk-norm that returns fp32 for bf16 input, as LayerNorm does under CUDA autocast."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return super().forward(x.float())


@torch.no_grad()
def test_keys_take_the_values_dtype_when_the_norm_returns_fp32() -> None:
    attention = Attention(8, 2, qk_norm=True)
    attention.q_norm, attention.k_norm = _Fp32Norm(4), _Fp32Norm(4)
    cast_matmul_weights(attention, torch.bfloat16)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        _, keys, values = attention.forward_map(torch.randn(1, 3, 8))
    assert keys.dtype == values.dtype == torch.bfloat16  # one cache dtype for K and V

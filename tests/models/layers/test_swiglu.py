"""SwiGLU feed-forward (DINOv2 ViT-g) and the ``ffn`` option of ``Block``."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.models.layers.block import Block
from kvtracker_sdk.models.layers.swiglu import SwiGLUFFN, swiglu_hidden_dim


def test_hidden_width_rule() -> None:
    assert swiglu_hidden_dim(4 * 1536) == 4096  # ViT-g/14: w12 is [8192, 1536]
    assert swiglu_hidden_dim(4 * 16) == 48  # 42 rounded up to a multiple of 8


def test_forward_is_silu_gate_times_value() -> None:
    torch.manual_seed(0)
    ffn = SwiGLUFFN(16, 64)
    x = torch.randn(2, 5, 16)
    gate, value = (x @ ffn.w12.weight.T + ffn.w12.bias).chunk(2, dim=-1)
    expected = (F.silu(gate) * value) @ ffn.w3.weight.T + ffn.w3.bias
    torch.testing.assert_close(ffn(x), expected, atol=1e-6, rtol=1e-6)


def test_block_ffn_option() -> None:
    names = set(Block(16, 2, ffn="swiglu", layerscale_init=1.0).state_dict())
    assert {"mlp.w12.weight", "mlp.w3.bias"} <= names and "mlp.fc1.weight" not in names
    assert "mlp.fc1.weight" in Block(16, 2).state_dict()  # the default stays the GELU MLP
    with pytest.raises(ConfigError, match="unknown ffn"):
        Block(16, 2, ffn="geglu")

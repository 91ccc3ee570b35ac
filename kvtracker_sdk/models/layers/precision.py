"""Mixed precision of the transformer trunks: bf16 matrix products, fp32 residual stream and norms.

The official Pi3 and DA3 pipelines run bf16 as ``torch.autocast(bfloat16)`` over an fp32 model:
every matrix product (``linear``, ``conv2d``, ``scaled_dot_product_attention``) gets bf16 operands,
while the residual stream stays fp32 (a bf16 branch output times an fp32 LayerScale, added to an
fp32 stream, is fp32) and the norms, LayerScales, position embeddings and register/camera tokens
keep fp32 parameters. Keeping the residual stream itself in bf16 deviates several times more from
fp32 (``benchmarks/README.md#figures-behind-the-code``).

We run the same recipe, with one change that does not alter a single value: the weights and biases
of the ``Linear``/``Conv2d`` layers are cast to bf16 once (``cast_matmul_weights``), so autocast finds
them already in bf16 and casts only activations. Autocast over fp32 weights would cast every weight
on every pass (for Pi3 ``large``, 959M parameters per tracking step).

Under CPU autocast the q/k LayerNorms return bf16 for bf16 input, so the official RoPE2D (which
follows the query's dtype) rounds its angles to bf16: ``matmul_dtype`` is that dtype, for RoPE
tables and for the K/V cache (K/V enter the attention in it, so a bf16 cache loses nothing).
"""

from __future__ import annotations

import contextlib

import torch
from torch import nn

__all__ = ["MATMUL_LAYERS", "cast_matmul_weights", "matmul_dtype", "trunk_autocast"]

# layers whose weights autocast feeds to a bf16 matrix product (their biases are cast with them)
MATMUL_LAYERS: tuple[type[nn.Module], ...] = (nn.Linear, nn.Conv2d)


def cast_matmul_weights(module: nn.Module, dtype: torch.dtype) -> None:
    """Cast the parameters of every ``MATMUL_LAYERS`` layer inside ``module`` to ``dtype``, in place.

    Everything else (norms, LayerScale gammas, embeddings, tokens) keeps its dtype.
    """
    for layer in module.modules():
        if isinstance(layer, MATMUL_LAYERS):
            for param in layer.parameters(recurse=False):
                param.data = param.data.to(dtype)


def trunk_autocast(
    dtype: torch.dtype, device: torch.device
) -> contextlib.AbstractContextManager[object]:
    """Autocast to ``dtype`` on ``device`` for a reduced-precision trunk; nothing for fp32.

    For fp32 it leaves the autocast state alone, so a caller's own ``torch.autocast`` still applies.
    """
    if dtype == torch.float32:
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=dtype)


def matmul_dtype(tensor: torch.Tensor) -> torch.dtype:
    """The dtype matrix products see for ``tensor``: autocast's where it is on, else its own."""
    device_type = tensor.device.type
    if torch.is_autocast_enabled(device_type):
        return torch.get_autocast_dtype(device_type)
    return tensor.dtype

"""Sizes as tensors, and a bicubic resize written with them: code that stays exportable.

Under ``torch.export`` (the ONNX exporter) an image's size is symbolic. Python arithmetic on it —
``float`` divisions, ``math.sqrt``, ``F.interpolate(scale_factor=...)``, ``torch.linspace(steps=
size)`` — makes the exporter fix it to the example's value, so the graph would take one
resolution only (and the pos-embed resize would be folded into a constant). Tensor arithmetic on
``size_tensor(size)`` keeps it symbolic.
"""

from __future__ import annotations

import torch

__all__ = ["bicubic_resize_matrix", "size_tensor"]

_CUBIC_A = -0.75  # PyTorch's (and OpenCV's) cubic convolution coefficient


def size_tensor(value: int, device: torch.device | str | None = None) -> torch.Tensor:
    """A size (int or symbolic) as a float64 scalar tensor."""
    return torch.full((), value, dtype=torch.float64, device=device)


def _near(x: torch.Tensor) -> torch.Tensor:  # cubic convolution weight for |x| <= 1
    return ((_CUBIC_A + 2) * x - (_CUBIC_A + 3)) * x * x + 1


def _far(x: torch.Tensor) -> torch.Tensor:  # cubic convolution weight for 1 < |x| < 2
    return ((_CUBIC_A * x - 5 * _CUBIC_A) * x + 8 * _CUBIC_A) * x - 4 * _CUBIC_A


def bicubic_resize_matrix(
    out_size: int, in_size: int, source_step: torch.Tensor, device: torch.device | str | None = None
) -> torch.Tensor:
    """[out_size, in_size] float32 matrix M such that ``M @ signal`` resizes a signal of
    ``in_size`` samples along one axis as ``upsample_bicubic2d(align_corners=False)`` does
    (no antialias): output sample i reads the source at ``(i + 0.5) * source_step - 0.5`` with
    the four cubic taps around it, indices clamped to the border.

    ``source_step`` (a scalar tensor) is PyTorch's ``1 / scale_factor`` when a scale factor is
    given, else ``in_size / out_size``. The matrix form is what makes a 2-D resize exportable
    with symbolic sizes (``M_h @ grid @ M_wᵀ``). The coordinates and weights are computed in
    float32 as in PyTorch's kernel (whose results it then equals to ~1e-6).
    """
    step = source_step.to(torch.float32)
    source = (torch.arange(out_size, dtype=torch.float32, device=device) + 0.5) * step - 0.5
    base = torch.floor(source)
    t = (source - base).unsqueeze(1)  # [out, 1]
    weights = torch.cat((_far(t + 1), _near(t), _near(1 - t), _far(2 - t)), dim=1)  # [out, 4]
    offsets = torch.arange(-1, 3, device=device)
    taps = (base.long().unsqueeze(1) + offsets).clamp(0, in_size - 1)  # [out, 4]
    columns = torch.arange(in_size, device=device)
    hits = (taps.unsqueeze(2) == columns).to(torch.float32)  # [out, 4, in]
    return (weights.unsqueeze(2) * hits).sum(dim=1)

"""bf16 deviation from fp32, summarised as (median, worst), for the per-family precision tests.

Each family's test runs one network three ways on the same inputs — fp32, the official bf16 recipe
(``torch.autocast('cpu', torch.bfloat16)`` over the fp32 weights) and the SDK's bf16
(``set_precision(torch.bfloat16)``) — and requires the SDK's median and worst deviation from fp32
to be no larger than the official recipe's, for every quantity (mapping and tracking poses,
points or depth), up to ``ROUNDING``: the fp32 heads' matrix products (MKL) may round the last bit
differently from run to run (their result depends on buffer alignment), which moves a deviation by
~1e-5 of itself; the bf16 schemes this test tells apart differ by 20 % to 170 %.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from typing import TypeVar

import torch

__all__ = [
    "Deviation",
    "absolute",
    "assert_as_accurate_as_autocast",
    "assert_sdk_no_worse",
    "relative",
    "three_ways",
]

Model = TypeVar("Model", bound=torch.nn.Module)
ROUNDING = 1e-3  # relative slack for fp32 run-to-run rounding (see the module docstring)


@dataclass(frozen=True)
class Deviation:
    """Median and worst of a deviation over all elements (pixels, pose entries)."""

    median: float
    worst: float

    @classmethod
    def of(cls, errors: torch.Tensor) -> Deviation:
        return cls(float(errors.median()), float(errors.max()))


def absolute(output: torch.Tensor, reference: torch.Tensor) -> Deviation:
    """|output - reference| per element (pose entries)."""
    return Deviation.of((output - reference).abs().flatten())


def relative(output: torch.Tensor, reference: torch.Tensor, *, vector: bool = False) -> Deviation:
    """|output - reference| / |reference| per element, or per vector over the last dim (points)."""
    if vector:
        return Deviation.of(((output - reference).norm(dim=-1) / reference.norm(dim=-1)).flatten())
    return Deviation.of(((output - reference).abs() / reference.abs()).flatten())


def three_ways(fp32_model: Model) -> Iterator[tuple[str, Model, AbstractContextManager[object]]]:
    """(name, model, context): fp32; the official recipe (autocast over fp32 weights); the SDK."""
    yield "fp32", fp32_model, nullcontext()
    yield "autocast", fp32_model, torch.autocast("cpu", dtype=torch.bfloat16)
    sdk = copy.deepcopy(fp32_model)
    set_precision: Callable[[torch.dtype], object] = sdk.set_precision  # type: ignore[assignment]
    set_precision(torch.bfloat16)
    yield "sdk", sdk, nullcontext()


def assert_sdk_no_worse(
    outputs: dict[str, dict[str, torch.Tensor]],
    measures: dict[str, Callable[[torch.Tensor, torch.Tensor], Deviation]],
    label: str,
) -> dict[str, tuple[Deviation, Deviation]]:
    """``outputs[way][quantity]`` for the ways of ``three_ways``; each quantity's deviation from
    fp32 under its measure. Fails unless the SDK's median and worst are <= autocast's (up to
    ``ROUNDING``); returns
    {quantity: (sdk, autocast)}."""
    report = {}
    for quantity, measure in measures.items():
        reference = outputs["fp32"][quantity]
        sdk = measure(outputs["sdk"][quantity], reference)
        official = measure(outputs["autocast"][quantity], reference)
        limit = 1.0 + ROUNDING
        assert sdk.median <= official.median * limit and sdk.worst <= official.worst * limit, (
            f"{label} {quantity}: SDK bf16 deviates {sdk}, the official autocast recipe {official}"
        )
        assert official.worst > 0, f"{label} {quantity}: autocast did not change the output"
        report[quantity] = (sdk, official)
    return report


@torch.no_grad()
def assert_as_accurate_as_autocast(
    model: Model,
    run: Callable[[Model], dict[str, torch.Tensor]],
    measures: dict[str, Callable[[torch.Tensor, torch.Tensor], Deviation]],
    label: str,
) -> None:
    """``run(network)`` (a family's map-and-track outputs by name) the three ways, then
    ``assert_sdk_no_worse`` on them."""
    outputs = {}
    for way, network, context in three_ways(model):
        with context:
            outputs[way] = run(network)
    assert_sdk_no_worse(outputs, measures, label)

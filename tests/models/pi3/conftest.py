"""Fixtures for the Pi3 tests: the golden reduced model and golden tensors from ``../shared``."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch
from safetensors.torch import load_file

from kvtracker_sdk.models.pi3 import Pi3, load_pi3
from tests.helpers import shared_path


@pytest.fixture(scope="session")
def golden_model() -> Pi3:
    """The reduced golden Pi3 (870k params), fp32, loaded strictly with an inferred config."""
    return load_pi3(shared_path("golden", "pi3", "weights.safetensors")).model


@pytest.fixture(scope="session")
def golden() -> Callable[..., dict[str, torch.Tensor]]:
    """``golden("case1", "outputs")`` -> the tensors of ``golden/pi3/case1/outputs.safetensors``."""
    cache: dict[tuple[str, ...], dict[str, torch.Tensor]] = {}

    def read(*parts: str) -> dict[str, torch.Tensor]:
        if parts not in cache:
            *folders, name = parts
            cache[parts] = load_file(shared_path("golden", "pi3", *folders, f"{name}.safetensors"))
        return cache[parts]

    return read

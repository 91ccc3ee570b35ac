"""Fixtures for the DA3 tests: the golden reduced model and golden tensors from ``../shared``."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch
from safetensors.torch import load_file

from kvtracker_sdk.models.da3 import DepthAnything3, load_da3
from tests.helpers import shared_path


@pytest.fixture(scope="session")
def golden_model() -> DepthAnything3:
    """The reduced golden DA3 (4.25M params, real DA3-Small key names), fp32, loaded strictly."""
    return load_da3(shared_path("golden", "da3", "weights.safetensors")).model


@pytest.fixture(scope="session")
def golden() -> Callable[[str], dict[str, torch.Tensor]]:
    """``golden("outputs")`` -> the tensors of ``golden/da3/outputs.safetensors``."""
    cache: dict[str, dict[str, torch.Tensor]] = {}

    def read(name: str) -> dict[str, torch.Tensor]:
        if name not in cache:
            cache[name] = load_file(shared_path("golden", "da3", f"{name}.safetensors"))
        return cache[name]

    return read

"""Fixtures of the CLI tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.helpers import shared_path


@pytest.fixture(scope="session")
def golden_weights() -> Path:
    """The small Pi3 checkpoint with the official key layout (random weights)."""
    return shared_path("golden", "pi3", "weights.safetensors")

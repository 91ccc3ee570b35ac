"""Shared fixtures: the ``../shared`` folder (golden vectors, real TUM data) and small models.

``../shared`` sits beside every developer checkout and CI clone but not beside a user's clone:
tests that need it skip with a message when it is absent — except under ``CI=true``, where its
absence is a failure (CI must never go green by skipping the parity tests).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.helpers import shared_path


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    return shared_path()


@pytest.fixture(scope="session")
def pi3_golden_dir() -> Path:
    return shared_path("golden", "pi3")


@pytest.fixture(scope="session")
def da3_golden_dir() -> Path:
    return shared_path("golden", "da3")


@pytest.fixture(scope="session")
def tum_dir() -> Path:
    return shared_path("data", "tum_fr2_desk")


@pytest.fixture(scope="session", autouse=True)
def one_torch_thread() -> Iterator[None]:
    """Run torch single-threaded in tests: the test models are tiny, and on a shared 2-core
    machine intra-op threads cost more in synchronisation than they win (measured 5-30x slower)."""
    try:
        import torch
    except ImportError:  # a layer-0-only environment: nothing to configure
        yield
        return
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)

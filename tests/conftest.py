"""Shared fixtures: the ``../shared`` folder (golden vectors, real TUM data) and small models.

``../shared`` sits beside every developer checkout and CI clone but not beside a user's clone:
tests that need it skip with a message when it is absent — except under ``CI=true``, where its
absence is a failure (CI must never go green by skipping the parity tests).
"""

from __future__ import annotations

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

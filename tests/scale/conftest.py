"""One Ray session for every scale-out test that needs it (starting Ray costs ~15 s here)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from tests.helpers import dev_dependency


@pytest.fixture(scope="session")
def ray_session() -> Iterator[Any]:
    dev_dependency("ray")  # imports ray first, as an app may: ensure_ray must cope
    from kvtracker_sdk.scale.ray_runtime import ensure_ray

    ray = ensure_ray(num_cpus=2)
    try:
        yield ray
    finally:
        ray.shutdown()

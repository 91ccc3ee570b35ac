"""One Ray session for every scale-out test that needs it (starting Ray costs ~15 s here)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from tests.helpers import dev_dependency

RAY_FIXTURE = "ray_session"


@pytest.fixture(scope="session")
def ray_session() -> Iterator[Any]:
    dev_dependency("ray")  # imports ray first, as an app may: ensure_ray must cope
    from kvtracker_sdk.scale.ray_runtime import ensure_ray

    ray = ensure_ray(num_cpus=2)
    try:
        yield ray
    finally:
        ray.shutdown()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    """After the session's last test that uses Ray, stop it rather than at the end of the session:
    an idle cluster (its daemons and the driver's threads) keeps burning ~2% of a core through
    every later test. ``ray.shutdown()`` is idempotent, so the fixture's own stays as it is."""
    result = yield
    users = [i for i in item.session.items if RAY_FIXTURE in getattr(i, "fixturenames", ())]
    if users and item is users[-1]:
        import sys

        ray = sys.modules.get("ray")
        if ray is not None and ray.is_initialized():
            ray.shutdown()
    return result

"""Shared fixtures: the ``../shared`` folder (golden vectors, real TUM data) and small models.

``../shared`` sits beside every developer checkout and CI clone but not beside a user's clone:
tests that need it skip with a message when it is absent — except under ``CI=true``, where its
absence is a failure (CI must never go green by skipping the parity tests).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

# The suite imports the SDK before torch, as an app should: it sets OMP_WAIT_POLICY=PASSIVE
# before torch's OpenMP loads (tests/test_threads.py relies on it), whichever test module is
# collected first and whatever it imports.
import kvtracker_sdk  # noqa: F401  isort: skip
from tests.helpers import dev_dependency, shared_path


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
    machine intra-op threads cost more in synchronisation than they win (measured 5-30x slower).
    ``KVTRACKER_TEST_TORCH_THREADS=N`` runs them on N threads instead (the thread variants of
    ``tests/cpu_variants.py``: a reduction split over threads rounds differently)."""
    try:
        import torch
    except ImportError:  # a layer-0-only environment: nothing to configure
        yield
        return
    threads = torch.get_num_threads()
    torch.set_num_threads(int(os.environ.get("KVTRACKER_TEST_TORCH_THREADS", "1")))
    yield
    torch.set_num_threads(threads)


@dataclass(frozen=True)
class OnnxExport:
    """A family's golden weights exported once per session by ``kvtracker export-onnx --json``."""

    family: str
    folder: Path
    weights: Path  # the golden checkpoint it was exported from
    exit_code: int  # of the command
    manifest_json: dict[str, Any]  # what the command printed


@pytest.fixture(scope="session")
def onnx_exports(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], OnnxExport]:
    """``onnx_exports(family)``: THE export of a family for the whole session (``pi3``, ``da3``).

    Exporting costs 30-60 s of CPU per family (``torch.onnx.export`` of five or six graphs, then
    the check against PyTorch), so every test that needs an export shares this one; it is made
    on first use through the command line, so the command's whole path runs once too.
    """
    made: dict[str, OnnxExport] = {}

    def export(family: str) -> OnnxExport:
        if family not in made:
            dev_dependency("onnxruntime")
            from tests.cli.invoke import invoke

            weights = shared_path("golden", family, "weights.safetensors")
            folder = tmp_path_factory.mktemp("onnx") / f"{family}-golden"
            result = invoke("export-onnx", "--weights", weights, "--out", folder, "--json")
            assert result.exit_code == 0, result.output
            made[family] = OnnxExport(
                family, folder, weights, result.exit_code, json.loads(result.stdout)
            )
        return made[family]

    return export


@pytest.fixture(scope="session")
def golden_onnx_dir(onnx_exports: Callable[[str], OnnxExport]) -> Path:
    """The golden Pi3 export of the session (``onnx_exports("pi3")``)."""
    return onnx_exports("pi3").folder


@pytest.fixture(scope="session")
def golden_da3_onnx_dir(onnx_exports: Callable[[str], OnnxExport]) -> Path:
    """The golden (reduced) DA3 export of the session (``onnx_exports("da3")``)."""
    return onnx_exports("da3").folder


@pytest.fixture(scope="session", autouse=True)
def onnx_export_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """``OnnxBackend.from_pretrained(checkpoint)`` exports into a session folder, not ~/.cache."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("KVTRACKER_CACHE_DIR", str(tmp_path_factory.mktemp("kvtracker-cache")))
        yield


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every test that needs a session ONNX export is ``slow`` (``-m "not slow"`` skips them all;
    the README's command runs them)."""
    for item in items:
        if "onnx_exports" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.slow)

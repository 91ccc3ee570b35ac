"""Shared fixtures: the ``../shared`` folder (golden vectors, real TUM data) and small models.

``../shared`` sits beside every developer checkout and CI clone but not beside a user's clone:
tests that need it skip with a message when it is absent — except under ``CI=true``, where its
absence is a failure (CI must never go green by skipping the parity tests).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

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


@pytest.fixture(scope="session")
def golden_onnx_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The golden Pi3 weights exported to ONNX (``kvtracker_sdk.export_onnx``), once per session.

    The export is checked against PyTorch as it is written; ~30-60 s on a 2-core CPU.
    """
    dev_dependency("onnxruntime")
    from kvtracker_sdk.export_onnx import export_onnx

    folder = tmp_path_factory.mktemp("onnx") / "pi3-golden"
    export_onnx(folder, weights=shared_path("golden", "pi3", "weights.safetensors"))
    return folder


@pytest.fixture(scope="session")
def golden_da3_onnx_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The golden (reduced) DA3 weights exported to ONNX, once per session; ~50 s on 2 cores."""
    dev_dependency("onnxruntime")
    from kvtracker_sdk.export_onnx import export_onnx

    folder = tmp_path_factory.mktemp("onnx") / "da3-golden"
    export_onnx(folder, weights=shared_path("golden", "da3", "weights.safetensors"))
    return folder


@pytest.fixture(scope="session", autouse=True)
def onnx_export_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """``OnnxBackend.from_pretrained(checkpoint)`` exports into a session folder, not ~/.cache."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("KVTRACKER_CACHE_DIR", str(tmp_path_factory.mktemp("kvtracker-cache")))
        yield

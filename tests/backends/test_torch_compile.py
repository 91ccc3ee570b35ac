"""The opt-in compiled tracking step: plumbing on a tiny Pi3 (Dynamo with the ``eager`` backend:
no C++ compilation, so the test stays cheap; Inductor itself is exercised by
``benchmarks/runtimes.py``), the typed error and the eager fallback."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.backends.torch_compile import CompileOptions, inductor_cache_dir
from kvtracker_sdk.errors import CompileError, ConfigError
from kvtracker_sdk.models.pi3 import Pi3
from kvtracker_sdk.types import HeadSet
from tests.models.pi3.factories import random_pi3

H, W = 28, 42


@pytest.fixture(scope="module")
def model() -> Pi3:
    return random_pi3(seed=7)


@pytest.fixture(scope="module")
def images() -> np.ndarray:
    return np.random.default_rng(3).integers(0, 256, size=(3, H, W, 3), dtype=np.uint8)


def test_compiled_step_equals_eager_and_reports(model: Pi3, images: np.ndarray) -> None:
    eager = TorchBackend(copy.deepcopy(model))
    compiled = TorchBackend(
        copy.deepcopy(model), compile=CompileOptions(backend="eager", freezing=False)
    )
    assert compiled.compile_report is not None and compiled.compile_report.status == "pending"
    assert "torch.compile-eager" in compiled.info.accelerations
    assert compiled.info.fingerprint == eager.info.fingerprint  # the same function
    cache = eager.map(images[:2]).cache
    expected = eager.track(images[2], cache, heads=HeadSet.CONFIDENCE)
    result = compiled.track(images[2], cache, heads=HeadSet.CONFIDENCE)
    report = compiled.compile_report
    assert report.status == "compiled" and report.first_call_s is not None
    # Dynamo's eager backend runs the same kernels: equal to fp32 rounding
    np.testing.assert_allclose(result.pose, expected.pose, atol=1e-6)
    np.testing.assert_allclose(result.confidence_map, expected.confidence_map, atol=1e-6)
    assert cache.num_keyframes == 2  # the compiled step only scratches the cache too


def test_missing_compiler_is_a_typed_error_or_an_eager_fallback(
    model: Pi3, images: np.ndarray, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path))  # process-wide: restored after
    monkeypatch.setenv("CXX", "no-such-compiler-kvtracker")
    with pytest.raises(CompileError, match="no-such-compiler-kvtracker"):
        TorchBackend(copy.deepcopy(model), compile=True)
    backend = TorchBackend(copy.deepcopy(model), compile=CompileOptions(fallback=True))
    report = backend.compile_report
    assert report is not None and report.status.startswith("eager:")
    assert report.cache_dir == tmp_path
    cache = backend.map(images[:2]).cache
    assert np.isfinite(backend.track(images[2], cache).pose).all()


def test_compile_options_are_checked(model: Pi3) -> None:
    with pytest.raises(ConfigError):
        TorchBackend(copy.deepcopy(model), compile="yes")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="freezing"):
        TorchBackend(copy.deepcopy(model), compile=CompileOptions(backend="eager"))


def test_inductor_cache_dir_follows_the_user_cache(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR", raising=False)
    monkeypatch.setenv("KVTRACKER_CACHE_DIR", "/x/kv")
    assert str(inductor_cache_dir()) == "/x/kv/inductor"
    monkeypatch.delenv("KVTRACKER_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", "/x/xdg")
    assert str(inductor_cache_dir()) == "/x/xdg/kvtracker_sdk/inductor"
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", "/x/ind")
    assert str(inductor_cache_dir()) == "/x/ind"
    assert str(inductor_cache_dir(CompileOptions(cache_dir="/x/opt"))) == "/x/opt"  # type: ignore[arg-type]


def test_the_products_attention_is_a_backend_option(model: Pi3, images: np.ndarray) -> None:
    eager = TorchBackend(copy.deepcopy(model))
    products = TorchBackend(copy.deepcopy(model), attention="products")
    assert "cached-attention-products" in products.info.accelerations
    assert products.info.fingerprint == eager.info.fingerprint
    cache = eager.map(images[:2]).cache
    np.testing.assert_allclose(
        products.track(images[2], cache).pose, eager.track(images[2], cache).pose, atol=1e-5
    )
    with pytest.raises(ConfigError, match="flash2"):
        TorchBackend(copy.deepcopy(model), attention="flash2")

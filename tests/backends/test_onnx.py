"""OnnxBackend: the Backend contract on the golden export, against TorchBackend on the same weights.

Both backends compute fp32; they may differ by float rounding only: poses atol 1e-5, confidence
atol 1e-5, local points atol 1e-4 + rtol 1e-4 (the golden tolerances).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from kvtracker_sdk.backends.base import Backend, MapResult
from kvtracker_sdk.backends.onnx import OnnxBackend
from kvtracker_sdk.backends.onnx_manifest import read_manifest
from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.errors import (
    BackendMismatchError,
    ConfigError,
    ImageDtypeError,
    ImageShapeError,
    MaskError,
    MissingDependencyError,
    ModelError,
    ResolutionChangedError,
    StateError,
)
from kvtracker_sdk.types import HeadSet
from tests.helpers import shared_path

H, W = 112, 154  # an 8 x 11 patch grid: 5 + 88 = 93 tokens per frame


@pytest.fixture(scope="module")
def onnx_backend(golden_onnx_dir: Path) -> OnnxBackend:
    return OnnxBackend(golden_onnx_dir, threads=1)


@pytest.fixture(scope="module")
def torch_backend() -> TorchBackend:
    return TorchBackend.from_pretrained(shared_path("golden", "pi3", "weights.safetensors"))


@pytest.fixture(scope="module")
def images() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, size=(4, H, W, 3), dtype=np.uint8)


@pytest.fixture(scope="module")
def onnx_map(onnx_backend: OnnxBackend, images: np.ndarray) -> MapResult:
    return onnx_backend.map(images[:3])


@pytest.fixture(scope="module")
def torch_map(torch_backend: TorchBackend, images: np.ndarray) -> MapResult:
    return torch_backend.map(images[:3])


def test_info_equals_the_torch_backends(
    onnx_backend: OnnxBackend, torch_backend: TorchBackend
) -> None:
    info, reference = onnx_backend.info, torch_backend.info
    assert isinstance(onnx_backend, Backend)
    assert (info.backend, info.family, info.dtype, info.device) == ("onnx", "pi3", "float32", "cpu")
    assert info.fingerprint == reference.fingerprint  # caches and maps cross between them
    assert info.layout == reference.layout
    assert (info.config_hash, info.weights_fingerprint) == (
        reference.config_hash,
        reference.weights_fingerprint,
    )
    assert info.tokens_per_frame(H, W) == reference.tokens_per_frame(H, W) == 93
    assert info.accelerations == ("CPUExecutionProvider",)


def test_map_matches_torch(onnx_map: MapResult, torch_map: MapResult) -> None:
    assert onnx_map.poses.dtype == np.float64 and onnx_map.poses.shape == (3, 4, 4)
    assert onnx_map.confidence.dtype == np.float32 and onnx_map.confidence.shape == (3, H, W)
    assert onnx_map.local_points.dtype == np.float32 and not onnx_map.poses.flags.writeable
    np.testing.assert_allclose(onnx_map.poses, torch_map.poses, atol=1e-5, rtol=0)
    np.testing.assert_allclose(onnx_map.confidence, torch_map.confidence, atol=1e-5, rtol=0)
    np.testing.assert_allclose(onnx_map.local_points, torch_map.local_points, atol=1e-4, rtol=1e-4)
    cache, reference = onnx_map.cache, torch_map.cache
    assert (cache.keyframe_ids, cache.tokens_per_frame, cache.dtype) == (
        (0, 1, 2),
        93,
        torch.float32,
    )
    for layer in range(cache.layout.num_layers):
        torch.testing.assert_close(cache.keys(layer), reference.keys(layer), atol=1e-5, rtol=0)
        torch.testing.assert_close(cache.values(layer), reference.values(layer), atol=1e-5, rtol=0)
    assert onnx_map.timings_ms["map"] > 0


@pytest.mark.parametrize("heads", list(HeadSet))
def test_track_on_either_backends_cache_matches_torch(
    onnx_backend: OnnxBackend,
    torch_backend: TorchBackend,
    onnx_map: MapResult,
    torch_map: MapResult,
    images: np.ndarray,
    heads: HeadSet,
) -> None:
    expected = torch_backend.track(images[3], torch_map.cache, heads=heads)
    before = onnx_map.cache.clone()
    for cache in (onnx_map.cache, torch_map.cache):  # a map made by either runtime
        result = onnx_backend.track(images[3], cache, heads=heads)
        np.testing.assert_allclose(result.pose, expected.pose, atol=1e-5, rtol=0)
        assert (result.confidence is None) == (heads is HeadSet.CAMERA)
        if result.confidence is not None:
            assert result.confidence == pytest.approx(expected.confidence, abs=1e-5)
            np.testing.assert_allclose(result.confidence_map, expected.confidence_map, atol=1e-5)
        assert (result.local_points is None) == (heads is not HeadSet.ALL)
        if result.local_points is not None:
            np.testing.assert_allclose(
                result.local_points, expected.local_points, atol=1e-4, rtol=1e-4
            )
        assert result.timings_ms["track"] > 0 and not result.pose.flags.writeable
    assert onnx_map.cache.equals(before)  # tracking only reads the cache


def test_bad_inputs_raise_typed_errors(
    onnx_backend: OnnxBackend, onnx_map: MapResult, images: np.ndarray
) -> None:
    with pytest.raises(ImageDtypeError):
        onnx_backend.map(images.astype(np.float32))
    with pytest.raises(ImageDtypeError):
        onnx_backend.map(images.tolist())  # type: ignore[arg-type]
    with pytest.raises(ImageShapeError, match="multiple of 14"):
        onnx_backend.map(images[:, :100])
    with pytest.raises(ImageShapeError):
        onnx_backend.track(images[:1], onnx_map.cache)
    with pytest.raises(MaskError):
        onnx_backend.map(images[:2], masks=np.ones((2, H, W), dtype=np.uint8))
    with pytest.raises(ResolutionChangedError):  # the map's keyframes are 112 x 154
        onnx_backend.track(images[0, :98, :140], onnx_map.cache)
    with pytest.raises(BackendMismatchError, match="bfloat16"):
        onnx_backend.track(images[3], onnx_map.cache.to(dtype=torch.bfloat16))


def test_other_layouts_are_refused(onnx_backend: OnnxBackend, images: np.ndarray) -> None:
    from tests.models.pi3.factories import random_pi3

    other = TorchBackend(random_pi3(seed=1))  # 2 global layers, 16-wide heads
    mapped = other.map(np.ascontiguousarray(images[:2, :28, :42]))
    with pytest.raises(BackendMismatchError, match="layout"):
        onnx_backend.track(images[0, :28, :42], mapped.cache)


def test_closed_backend_refuses_calls(golden_onnx_dir: Path, images: np.ndarray) -> None:
    backend = OnnxBackend(golden_onnx_dir, threads=1)
    backend.close()
    backend.close()  # idempotent
    with pytest.raises(StateError, match="closed"):
        backend.map(images[:1])


def test_devices_and_providers(golden_onnx_dir: Path) -> None:
    with pytest.raises(ConfigError, match="unknown ONNX device"):
        OnnxBackend(golden_onnx_dir, device="tpu")
    with pytest.raises(MissingDependencyError, match="CUDAExecutionProvider"):
        OnnxBackend(golden_onnx_dir, device="cuda:0")  # onnxruntime here is the CPU build
    explicit = OnnxBackend.from_pretrained(golden_onnx_dir, providers=["CPUExecutionProvider"])
    assert explicit.info.accelerations == ("CPUExecutionProvider",)


def test_folders_that_are_not_exports_are_refused(golden_onnx_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(ModelError, match="kvtracker export-onnx"):
        OnnxBackend(tmp_path)
    with pytest.raises(ModelError, match="not an ONNX export"):
        OnnxBackend(shared_path("golden", "pi3", "weights.safetensors"))
    broken = tmp_path / "broken"
    shutil.copytree(golden_onnx_dir, broken)
    manifest = json.loads((broken / "manifest.json").read_text())
    manifest["weights_fingerprint"] = "0" * 32  # other weights under the same fingerprint
    (broken / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ModelError, match="fingerprint"):
        OnnxBackend(broken)
    (broken / "head_conf.onnx").unlink()
    with pytest.raises(ModelError, match="head_conf.onnx"):
        OnnxBackend(broken)
    for family, message in (("nerf", "family 'nerf'"), ("da3", "no graph for .'head_depth'")):
        (broken / "manifest.json").write_text(json.dumps({**manifest, "family": family}))
        with pytest.raises(ModelError, match=message):  # a manifest naming another family
            OnnxBackend(broken)
    manifest["format_version"] = 99
    (broken / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ModelError, match="version 99"):
        OnnxBackend(broken)


def test_onnx_backend_exports_a_checkpoint_once(
    golden_onnx_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from kvtracker_sdk.export_onnx import reuse

    weights = shared_path("golden", "pi3", "weights.safetensors")
    slot = tmp_path / f"pi3-{read_manifest(golden_onnx_dir).weights_fingerprint}"
    exports: list[Path] = []

    def export(model: object, folder: Path, **options: object) -> None:  # the real one: 30 s
        exports.append(folder)
        shutil.copytree(golden_onnx_dir, folder, dirs_exist_ok=True)

    monkeypatch.setattr(reuse, "export_model", export)
    first = reuse.onnx_backend(weights, cache_dir=tmp_path, threads=1)
    again = reuse.onnx_backend(weights, cache_dir=tmp_path, threads=1)
    assert first.folder == again.folder == slot and exports == [slot]  # exported once
    assert first.info.fingerprint == TorchBackend.from_pretrained(weights).info.fingerprint
    manifest = json.loads((slot / "manifest.json").read_text())
    (slot / "manifest.json").write_text(json.dumps({**manifest, "format_version": 0}))
    reuse.onnx_backend(weights, cache_dir=tmp_path, threads=1)
    assert exports == [slot, slot]  # a stale export in the slot is replaced
    assert reuse.onnx_backend(slot, threads=1).folder == slot  # a folder loads as is
    assert OnnxBackend.from_pretrained(slot, threads=1).folder == slot
    with pytest.raises(ModelError, match="not an ONNX export"):  # exporting is a layer above
        OnnxBackend.from_pretrained(weights)

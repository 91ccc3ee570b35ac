"""OnnxBackend on the golden Pi3 export: typed errors, refusals, devices, closing, exporting a
checkpoint once (identity, mapping and tracking against TorchBackend, for both families:
``test_onnx_backend_families.py``).

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

from kvtracker_sdk.backends.base import MapResult
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
from tests.helpers import shared_path

H, W = 112, 154  # an 8 x 11 patch grid: 5 + 88 = 93 tokens per frame


@pytest.fixture(scope="module")
def onnx_backend(golden_onnx_dir: Path) -> OnnxBackend:
    return OnnxBackend(golden_onnx_dir, threads=1)


@pytest.fixture(scope="module")
def images() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, size=(4, H, W, 3), dtype=np.uint8)


@pytest.fixture(scope="module")
def onnx_map(onnx_backend: OnnxBackend, images: np.ndarray) -> MapResult:
    return onnx_backend.map(images[:3])


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


def test_a_pruned_cache_tracks_as_in_torch_and_unequal_layers_are_refused(
    onnx_backend: OnnxBackend, onnx_map: MapResult, images: np.ndarray
) -> None:
    from kvtracker_sdk.cache.pruning import prune_cache

    cache = onnx_map.cache.clone()
    prune_cache(cache, keep_ratio=0.5, extra_tokens_per_frame=onnx_backend.info.extra_tokens_per_frame)
    torch_backend = TorchBackend.from_pretrained(shared_path("golden", "pi3", "weights.safetensors"))
    expected = torch_backend.track(images[3], cache.clone())
    tracked = onnx_backend.track(images[3], cache)
    np.testing.assert_allclose(tracked.pose, expected.pose, atol=1e-5)
    uneven = onnx_map.cache.clone()
    uneven.keep_tokens([torch.arange(uneven.layer_length(i) - i) for i in range(uneven.layout.num_layers)])
    with pytest.raises(BackendMismatchError, match="past_length"):
        onnx_backend.track(images[3], uneven)

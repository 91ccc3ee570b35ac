"""Export folders are verified, not trusted: sha256 of every file, paths inside the folder.

All cases damage a COPY of the session's golden export (graphs hard-linked, weights copied, the
manifest rewritten); no case exports again (``reuse.export_model`` is replaced by a copy of the
golden folder where a re-export is expected).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from kvtracker_sdk.backends.onnx import OnnxBackend
from kvtracker_sdk.backends.onnx_manifest import MANIFEST_NAME, WEIGHTS_NAME, read_manifest
from kvtracker_sdk.errors import ModelError
from tests.helpers import shared_path


def copy_export(source: Path, target: Path) -> Path:
    """A copy whose graphs are hard links (never modified in place) and whose weights and
    manifest are real copies (the tests edit those)."""
    target.mkdir(parents=True)
    for entry in source.iterdir():
        if entry.suffix == ".onnx":
            os.link(entry, target / entry.name)
        else:
            shutil.copyfile(entry, target / entry.name)
    return target


def scale_weights(folder: Path, factor: float) -> None:
    weights = np.fromfile(folder / WEIGHTS_NAME, dtype=np.float32)
    (weights * np.float32(factor)).tofile(folder / WEIGHTS_NAME)


def edit_manifest(folder: Path, **changes: Any) -> dict[str, Any]:
    manifest = json.loads((folder / MANIFEST_NAME).read_text())
    manifest.update(changes)
    (folder / MANIFEST_NAME).write_text(json.dumps(manifest))
    return manifest


@pytest.fixture
def copied(golden_onnx_dir: Path, tmp_path: Path) -> Path:
    return copy_export(golden_onnx_dir, tmp_path / "export")


def test_weights_scaled_by_1_5_are_refused(copied: Path) -> None:
    scale_weights(copied, 1.5)
    with pytest.raises(ModelError, match=r"\['weights.bin'\] changed since the export"):
        OnnxBackend(copied)


def test_a_swapped_graph_is_refused(copied: Path) -> None:
    camera = copied / "head_camera.onnx"
    camera.unlink()  # a hard link: replace it, never write through it
    shutil.copyfile(copied / "head_conf.onnx", camera)
    with pytest.raises(ModelError, match=r"\['head_camera.onnx'\] changed since the export"):
        OnnxBackend(copied)


@pytest.mark.parametrize("where", ["absolute", "parent"])
def test_graph_paths_outside_the_folder_are_refused(
    copied: Path, golden_onnx_dir: Path, where: str
) -> None:
    manifest = json.loads((copied / MANIFEST_NAME).read_text())
    outside = (
        str(golden_onnx_dir / "encoder.onnx")
        if where == "absolute"
        else os.path.relpath(golden_onnx_dir / "encoder.onnx", copied)
    )
    manifest["graphs"]["encoder"]["file"] = outside
    digests = manifest.get("sha256", {})
    digests[outside] = digests.pop("encoder.onnx", None)  # the digest agrees with the file
    (copied / MANIFEST_NAME).write_text(json.dumps(manifest))
    with pytest.raises(ModelError, match="outside its folder"):
        OnnxBackend(copied)


def test_a_manifest_without_digests_is_refused(copied: Path) -> None:
    manifest = json.loads((copied / MANIFEST_NAME).read_text())
    manifest.pop("sha256", None)
    (copied / MANIFEST_NAME).write_text(json.dumps({**manifest, "format_version": 1}))
    with pytest.raises(ModelError, match="format version 1, this SDK reads version 2"):
        OnnxBackend(copied)


def test_onnx_backend_exports_again_over_a_poisoned_cached_folder(
    golden_onnx_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from kvtracker_sdk.export_onnx import reuse

    weights = shared_path("golden", "pi3", "weights.safetensors")
    slot = tmp_path / f"pi3-{read_manifest(golden_onnx_dir).weights_fingerprint}"
    copy_export(golden_onnx_dir, slot)
    scale_weights(slot, 1.5)  # the cached export's weights, poisoned
    exports: list[Path] = []

    def export(model: object, folder: Path, **options: object) -> None:  # the real one: 60 s
        exports.append(folder)
        shutil.rmtree(folder)
        copy_export(golden_onnx_dir, folder)

    monkeypatch.setattr(reuse, "export_model", export)
    backend = reuse.onnx_backend(weights, cache_dir=tmp_path, threads=1)
    assert exports == [slot] and backend.folder == slot
    from kvtracker_sdk.backends import onnx_integrity

    onnx_integrity.verify_files(slot, read_manifest(slot).sha256)  # the clean export now


def test_a_file_is_hashed_once_per_process_until_it_changes(
    copied: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from kvtracker_sdk.backends import onnx_integrity

    hashed: list[str] = []
    real = onnx_integrity._sha256

    def counting(path: Path) -> str:
        hashed.append(path.name)
        return real(path)

    monkeypatch.setattr(onnx_integrity, "_sha256", counting)
    expected = read_manifest(copied).sha256
    onnx_integrity.forget_verified()
    onnx_integrity.verify_files(copied, expected)
    assert sorted(hashed) == sorted(expected)
    onnx_integrity.verify_files(copied, expected)  # the fast path: nothing hashed again
    assert len(hashed) == len(expected)
    stat = (copied / WEIGHTS_NAME).stat()
    os.utime(copied / WEIGHTS_NAME, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))
    onnx_integrity.verify_files(copied, expected)  # touched: hashed again, and still intact
    assert hashed[len(expected) :] == [WEIGHTS_NAME]

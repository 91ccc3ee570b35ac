"""An export folder whose manifest lies about its files is refused, though every sha256 holds.

Accepted before: a wrong ``weights_bytes``, the layout edited (``num_heads`` 2 -> 4), the config
edited with its ``config_hash`` kept, ``head_conf`` and ``head_points`` files swapped. Uses the
session's export (``onnx_exports``): no export of its own.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest

from kvtracker_sdk.backends.onnx_manifest import read_manifest
from kvtracker_sdk.errors import KVTrackerError, ModelError
from tests.backends.export_edits import _get, _numeric_paths, _set, edited_folder, edited_manifests
from tests.conftest import OnnxExport

DEFAULT_EDITS = 40  # seeded, cheap (the manifest is read, no session is made)


def _manifest(export: OnnxExport) -> dict:
    return json.loads((export.folder / "manifest.json").read_text())


@pytest.mark.parametrize("family", ["pi3", "da3"])
def test_each_edited_claim_reported_is_refused(
    onnx_exports: Callable[[str], OnnxExport], tmp_path: Path, family: str
) -> None:
    export = onnx_exports(family)
    original = _manifest(export)
    read_manifest(edited_folder(export.folder, tmp_path / "ok", original))  # unedited: fine

    def refused(edit: Callable[[dict], None], field: str) -> None:
        manifest = json.loads(json.dumps(original))
        edit(manifest)
        with pytest.raises(ModelError, match=field):
            read_manifest(edited_folder(export.folder, tmp_path / "edited", manifest))

    refused(lambda m: m.update(weights_bytes=m["weights_bytes"] + 1), "weights_bytes")
    refused(lambda m: m["layout"].update(num_heads=2 * m["layout"]["num_heads"]), "layout")
    first = _numeric_paths(original["config"])[0]  # e.g. a width: the hash is kept as it was
    refused(lambda m: _set(m["config"], first, _get(m["config"], first) + 1), "config_hash")


def test_head_files_swapped_between_roles_are_refused_by_the_backend(
    onnx_exports: Callable[[str], OnnxExport], tmp_path: Path
) -> None:
    from kvtracker_sdk.backends.onnx import OnnxBackend

    export = onnx_exports("pi3")
    manifest = _manifest(export)
    graphs = manifest["graphs"]
    graphs["head_conf"]["file"], graphs["head_points"]["file"] = (
        graphs["head_points"]["file"], graphs["head_conf"]["file"])
    with pytest.raises(ModelError, match="wrong role"):
        OnnxBackend(edited_folder(export.folder, tmp_path / "swapped", manifest))


def test_seeded_manifest_edits_are_all_refused(
    onnx_exports: Callable[[str], OnnxExport], tmp_path: Path
) -> None:
    export = onnx_exports("pi3")
    accepted, untyped = [], []
    for name, manifest in edited_manifests(_manifest(export), DEFAULT_EDITS, seed=34):
        if "swap" in name:
            continue  # a swap is caught when the runtime reads the graphs (test above)
        try:
            read_manifest(edited_folder(export.folder, tmp_path / "edited", manifest))
            accepted.append(name)
        except KVTrackerError:
            pass
        except Exception as exc:  # noqa: BLE001 - counting what escapes
            untyped.append((name, type(exc).__name__))
    assert (accepted, untyped) == ([], [])

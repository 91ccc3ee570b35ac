"""Smoke test of ``benchmarks/onnx_vs_torch.py`` (no timing checks) on the golden Pi3 checkpoint,
whose export the session already made (``onnx_exports``): the benchmark finds it in
``--onnx-dir/<config>`` with the same fingerprint and reuses it instead of exporting again."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

from benchmarks.onnx_vs_torch import main, markdown_table
from tests.conftest import OnnxExport
from tests.helpers import dev_dependency


@pytest.mark.slow
def test_main_times_and_reuses_the_export(
    tmp_path: Path, onnx_exports: Callable[[str], OnnxExport]
) -> None:
    dev_dependency("onnxruntime")
    export = onnx_exports("pi3")
    shutil.copytree(export.folder, tmp_path / "onnx" / "tiny")  # int8 graphs go beside it
    manifest = tmp_path / "onnx" / "tiny" / "manifest.json"
    stamp = manifest.stat().st_mtime_ns
    # --keep-denormals: flushing them is process-wide CPU state (hypothesis tests detect it)
    argv = ["--config", "tiny", "--size", "56", "--keyframes", "1", "2", "--heads", "camera",
            "--threads", "1", "--int8", "--warmup", "0", "--repeats", "2", "--keep-denormals",
            "--onnx-dir", str(tmp_path / "onnx"), "--weights", str(export.weights),
            "--name", "smoke", "--out-dir", str(tmp_path)]  # fmt: skip
    result = main(argv)

    written = json.loads((tmp_path / "smoke.json").read_text())
    assert written == json.loads(json.dumps(result))
    assert [(row["keyframes"], row["heads"]) for row in written["rows"]] == [(1, "camera"), (2, "camera")]
    for row in written["rows"]:
        for variant in ("torch_fp32", "onnx_fp32", "onnx_int8"):
            assert len(row[variant]["wall"]) == 2
        errors = row["pose_max_abs_diff_vs_torch"]
        assert errors["torch_fp32"] == 0.0 and errors["onnx_fp32"] < 1e-4  # the same fp32 function
        assert errors["onnx_int8"] < 0.1  # int8 rounding moves the pose a little, not wholesale
    table = markdown_table(written).splitlines()
    assert len(table) == 2 + 2 and table[-1].startswith("| tiny | 2 | camera |")

    assert manifest.stat().st_mtime_ns == stamp  # same weights: the session's export is reused
    int8 = {p: p.stat().st_mtime_ns for p in (tmp_path / "onnx" / "tiny-int8").glob("*.onnx")}
    assert int8  # the first run quantised the tracking graphs beside the export
    main(argv[:-4] + ["--keyframes", "1", "--name", "again", "--out-dir", str(tmp_path)])
    assert manifest.stat().st_mtime_ns == stamp  # same weights: the export is reused
    assert {p: p.stat().st_mtime_ns for p in int8} == int8  # and so are the int8 graphs

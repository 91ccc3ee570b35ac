"""Smoke test of ``benchmarks/onnx_vs_torch.py`` on the tiny preset (no timing checks)."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.onnx_vs_torch import main, markdown_table
from tests.helpers import dev_dependency


def test_main_exports_times_and_reuses_the_export(tmp_path: Path) -> None:
    dev_dependency("onnxruntime")
    # --keep-denormals: flushing them is process-wide CPU state (hypothesis tests detect it)
    argv = ["--config", "tiny", "--size", "56", "--keyframes", "1", "2", "--heads", "camera",
            "--threads", "1", "--int8", "--warmup", "0", "--repeats", "2", "--keep-denormals",
            "--onnx-dir", str(tmp_path / "onnx"), "--name", "smoke", "--out-dir", str(tmp_path)]  # fmt: skip
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

    manifest = tmp_path / "onnx" / "tiny" / "manifest.json"
    stamp = manifest.stat().st_mtime_ns
    main(argv[:-4] + ["--keyframes", "1", "--name", "again", "--out-dir", str(tmp_path)])
    assert manifest.stat().st_mtime_ns == stamp  # same weights: the export is reused

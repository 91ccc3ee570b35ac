"""``benchmarks/gpu_check.py --dry-run``: the device script's code path on the CPU with a tiny
model (what a lent GPU runs, minus CUDA: graphs fall back to eager there). Sections parity, bf16
and session read ``../shared`` and take minutes on a CPU: they run in ``--dry-run`` by hand."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.gpu_check import main

VARIANTS = {"eager-bf16", "graph-bf16", "graph-flat-bf16", "graph-masked-bf16", "official-bf16"}


def test_dry_run_writes_every_variant(tmp_path: Path) -> None:
    main(["--dry-run", "--sections", "device", "peak", "upload", "steps", "--models", "pi3-tiny",
          "--keyframes", "2", "--heads", "camera", "--out", str(tmp_path)])  # fmt: skip
    result = json.loads((tmp_path / "gpu_check_dry_run.json").read_text())
    assert result["errors"] == {} and result["dry_run"]
    sections = result["sections"]
    assert sections["device"]["torch"] and sections["peak"]["bf16_flops_per_s"] > 0
    assert set(sections["upload"]) == {"frame", "pageable", "pinned"}
    [point] = sections["steps"]["points"]
    assert (point["model"], point["keyframes"], point["heads"]) == ("pi3-tiny", 2, "camera")
    assert set(point["rows"]) == VARIANTS and point["flops"] > 0
    for label, row in point["rows"].items():
        assert row["median_s"] > 0 and len(point["samples"][label]) == 2
        if label.startswith("graph"):  # eager off CUDA: the same step
            assert row["pose_deviation_vs_eager"] == 0.0
    # the official recipe (autocast over fp32 weights) is bit-equal to the SDK's bf16 on the CPU
    assert point["rows"]["official-bf16"]["pose_deviation_vs_eager"] < 1e-6
    reports = sections["steps"]["graph_reports"]["pi3-tiny"]
    assert all("graphs are CUDA only" in r["errors"][0] for r in reports.values())
    assert "| pi3-tiny | 2 | camera |" in (tmp_path / "gpu_check_dry_run.md").read_text()

"""Smoke test of ``benchmarks/runtimes.py`` on tiny Pi3 / DA3 configs (no timing checks): the
JSON and table, the official step computing the SDK's function, the FLOP count against the
arithmetic model of ``benchmarks/flops.py``."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.flops import tracking_step_flops
from benchmarks.runtimes import main, markdown_table
from benchmarks.tracking_vs_recompute import PRESETS
from kvtracker_sdk.types import HeadSet

SIZE = 56  # 4x4 patches


def test_main_writes_json_and_the_official_step_matches(tmp_path: Path) -> None:
    argv = ["--models", "pi3-tiny", "da3-tiny", "--sizes", str(SIZE), "--keyframes", "2",
            "--heads", "camera", "--variants", "torch-fp32", "torch-bf16", "products-bf16",
            "official-bf16", "official-fp32", "--rounds", "1", "--warmup", "0",
            "--out-dir", str(tmp_path), "--name", "smoke"]  # fmt: skip
    result = main(argv)
    written = json.loads((tmp_path / "smoke.json").read_text())
    assert written == json.loads(json.dumps(result))
    points = {p["model"]: p for p in written["points"]}
    assert set(points) == {"pi3-tiny", "da3-tiny"}
    for point in points.values():
        rows = point["rows"]
        assert set(rows) == {"torch-fp32", "torch-bf16", "products-bf16", "official-bf16",
                             "official-fp32"}  # fmt: skip
        # cat + SDPA over fp32 weights is the SDK's fp32 step, to float rounding
        assert rows["official-fp32"]["pose_deviation"] < 1e-5
        assert 0 < rows["official-bf16"]["pose_deviation"] < 0.1  # bf16 does change the pose
        assert rows["official-bf16"]["speedup_vs_official_bf16"] == 1.0
        assert set(point["peak_flops_per_s"]) == {"bf16", "fp32"}
        assert all(r["fraction_of_limit"] > 0 for r in rows.values())
    # the FLOP counter (with the CPU flash-attention formula) agrees with the arithmetic model,
    # which leaves out only the camera head's 3x3 products
    expected = tracking_step_flops(PRESETS["tiny"](), SIZE, SIZE, 2, HeadSet.CAMERA).total
    assert abs(points["pi3-tiny"]["flops"] - expected) / expected < 1e-3
    assert "official-bf16" in markdown_table(written["points"])

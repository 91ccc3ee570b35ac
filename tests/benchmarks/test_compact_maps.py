"""Smoke test of ``benchmarks/compact_maps.py`` on tiny Pi3 and DA3 configs (no timing checks)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.compact_maps import VARIANTS, Variant, main


def test_main_writes_every_variant_side_by_side(tmp_path: Path) -> None:
    measured: list[int] = []
    VARIANTS["probe"] = Variant(  # a plugged-in variant with its own numbers
        "probe", storage="int8", measure=lambda setup, cache: {"probe_keyframes": cache.num_keyframes}
    )
    try:
        result = main(["--models", "pi3-tiny", "da3-tiny", "--keyframes", "1", "2",
                       "--variants", "int8", "fp8", "int8-full", "probe", "--rounds", "2", "--skip-accuracy",
                       "--out-dir", str(tmp_path), "--name", "smoke"])  # fmt: skip
    finally:
        del VARIANTS["probe"]
    written = json.loads((tmp_path / "smoke.json").read_text())
    assert written == json.loads(json.dumps(result)) and written["accuracy"] == []
    assert len(written["load_average_start"]) == 3 and len(written["load_average_end"]) == 3
    rows = written["rows"]
    assert [(r["model"], r["keyframes"], r["variant"]) for r in rows] == [
        (model, n, variant) for model in ("pi3-tiny", "da3-tiny") for n in (1, 2)
        for variant in ("dense", "int8", "fp8", "int8-full", "probe")
    ]  # fmt: skip
    encodings = {"dense": "full", "int8-full": "full", "int8": "compact", "fp8": "compact"}
    for row in rows:
        assert len(row["step_cpu_s"]) == 2 and row["step_cpu_median_s"] > 0
        assert row["file_bytes"] > row["file_kv_bytes"] == row["cache_bytes"]
        if row["variant"] == "dense":
            assert row["storage"] == "bfloat16" and row["kv_ratio"] == row["step_ratio_median"] == 1
        else:  # head_dim 16: 16 data bytes + 1 scale byte vs 32
            assert row["kv_ratio"] == 32 / 17 and row["file_ratio"] > 1
        measured += [row["probe_keyframes"]] if row["variant"] == "probe" else []
        # the parts add up to the file; DA3's points are depth x rays, Pi3's are xyz
        parts = row["file_bytes_per_keyframe"]
        assert sum(parts.values()) * row["keyframes"] == pytest.approx(row["file_bytes"])
        assert parts["kv"] * row["keyframes"] == row["file_kv_bytes"]
        expected = encodings.get(row["variant"], "compact")
        if expected == "compact":
            expected += "-depth" if row["model"] == "da3-tiny" else "-xyz"
        assert row["keyframe_encoding"] == expected
    by_name = {(r["model"], r["keyframes"], r["variant"]): r for r in rows}
    for model in ("pi3-tiny", "da3-tiny"):  # the compact payload is what makes int8 smaller
        assert by_name[model, 2, "int8"]["file_ratio"] > by_name[model, 2, "int8-full"]["file_ratio"]
    assert measured == [1, 2, 1, 2]

"""Smoke test of ``benchmarks/tracking_vs_recompute.py`` and its FLOP model (no timing checks)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from torch.utils.flop_counter import FlopCounterMode, sdpa_flop_count

from benchmarks.flops import recompute_flops, tracking_step_flops
from benchmarks.tracking_report import markdown_table
from benchmarks.tracking_vs_recompute import PRESETS, build_model, main, random_cache
from kvtracker_sdk.types import HeadSet

SIZE = 56  # 4x4 patches: T = 5 + 16 tokens per frame
FRAME = (42, 56)  # --size H W: 3x4 patches, T = 5 + 12


def test_main_writes_json_and_plot(tmp_path: Path) -> None:
    argv = ["--config", "tiny", "--size", *map(str, FRAME), "--dtype", "fp32", "--keyframes", "1", "2",
            "--max-recompute", "1", "--warmup", "0", "--repeats", "1", "--threads", "1",
            "--name", "smoke", "--out-dir", str(tmp_path)]  # fmt: skip
    result = main(argv)

    written = json.loads((tmp_path / "smoke.json").read_text())
    assert written == json.loads(json.dumps(result))
    assert written["resolution"] == list(FRAME) and written["threads"] == 1
    assert written["tokens_per_frame"] == 5 + 12
    assert written["real_path_check_max_pose_diff"] <= 1e-3
    assert [row["keyframes"] for row in written["rows"]] == [1, 2]
    for row in written["rows"]:
        for heads in ("camera", "all"):
            assert len(row[f"track_{heads}"]["wall"]) == 1
            assert row[f"track_{heads}_flops"]["total"] > 0
    # recompute only up to --max-recompute
    assert "recompute_camera" in written["rows"][0]
    assert "recompute_camera" not in written["rows"][1]
    table = markdown_table(written, "camera").splitlines()
    assert len(table) == 2 + 2 and table[-1].startswith("| 2 |")
    assert (tmp_path / "smoke.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("heads", list(HeadSet))
def test_flop_model_scaling(heads: HeadSet) -> None:
    config = PRESETS["mid"]()
    track = [tracking_step_flops(config, 308, 308, n, heads) for n in (1, 2, 4, 8)]
    recompute = [recompute_flops(config, 308, 308, m, heads) for m in (2, 4, 8)]
    # cached step: only the global attention depends on N, linearly in N + 1
    assert {(f.encoder, f.decoder_linear, f.head_decoders, f.heads) for f in track} == {
        (track[0].encoder, track[0].decoder_linear, track[0].head_decoders, track[0].heads)
    }
    per_key_frame = track[0].global_attention / 2
    for n, flops in zip((1, 2, 4, 8), track, strict=True):
        assert flops.global_attention == pytest.approx(per_key_frame * (n + 1), rel=1e-12)
    # recompute on M frames: global attention quadratic in M, everything else linear
    for small, large in zip(recompute, recompute[1:], strict=False):
        assert large.global_attention == pytest.approx(4 * small.global_attention, rel=1e-12)
        assert large.encoder == pytest.approx(2 * small.encoder, rel=1e-12)
        assert large.head_decoders == pytest.approx(2 * small.head_decoders, rel=1e-12)
    # one frame tracked against no keyframe costs what a one-frame forward costs
    assert tracking_step_flops(config, 308, 308, 0, heads).total == pytest.approx(
        recompute_flops(config, 308, 308, 1, heads).total, rel=1e-12
    )


def _counted_flops(fn: object) -> int:
    """FLOPs that ``torch.utils.flop_counter`` counts, with the CPU SDPA kernel registered."""
    mapping = {
        torch.ops.aten._scaled_dot_product_flash_attention_for_cpu: (
            lambda q, k, v, *args, **kwargs: sdpa_flop_count(q, k, v)
        )
    }
    with torch.no_grad(), FlopCounterMode(display=False, custom_mapping=mapping) as counter:
        fn()  # type: ignore[operator]
    return int(counter.get_total_flops())


@pytest.mark.parametrize("heads", list(HeadSet))
def test_flop_model_matches_torch_flop_counter(heads: HeadSet) -> None:
    model = build_model(PRESETS["tiny"](), torch.float32)
    config, keyframes = model.config, 3
    cache = random_cache(model, keyframes, model.tokens_per_frame(SIZE, SIZE))
    generator = torch.Generator().manual_seed(0)
    query = torch.rand(1, 3, SIZE, SIZE, generator=generator)
    frames = torch.rand(1, keyframes + 1, 3, SIZE, SIZE, generator=generator)
    counted_track = _counted_flops(lambda: model.forward_track(query, cache, heads=heads))
    counted_full = _counted_flops(lambda: model(frames, heads=heads))
    # the model leaves out only the camera head's 3x3 products (108 FLOPs per frame)
    modelled_track = tracking_step_flops(config, SIZE, SIZE, keyframes, heads).total
    modelled_full = recompute_flops(config, SIZE, SIZE, keyframes + 1, heads).total
    assert modelled_track == pytest.approx(counted_track, rel=1e-4)
    assert modelled_full == pytest.approx(counted_full, rel=1e-4)

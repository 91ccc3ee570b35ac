"""``kvtracker tune`` on the small golden Pi3 checkpoint (torch candidates), and ``--backend auto``
of ``kvtracker track`` reading the choice it kept."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from kvtracker_sdk.cli.track import _resolve_auto
from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.runs.backends import BackendKind, ComputeDtype
from tests.cli.invoke import invoke


def test_tune_keeps_a_choice_that_track_auto_uses(
    golden_weights: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("KVTRACKER_CACHE_DIR", str(tmp_path))
    config = TrackerConfig().updated(resolution=224, keyframing={"budget": {"max_keyframes": 2}})
    # nothing tuned yet: torch float32, automatic threads (as before)
    untuned = _resolve_auto(BackendKind.AUTO, str(golden_weights), "cpu", None, None, config)
    assert untuned[:3] == (BackendKind.TORCH, ComputeDtype.FLOAT32, None)
    assert "kvtracker tune --weights" in untuned[3]
    result = invoke("tune", "--weights", golden_weights, "--runtime", "torch", "--resolution",
                    224, "--keyframes", 2, "--seconds", 0.2, "--json")  # fmt: skip
    assert result.exit_code == 0, result.output
    record = json.loads(result.stdout)
    chosen = record["chosen"]
    assert chosen["runtime"] == "torch" and chosen["dtype"] in ("float32", "bfloat16")
    assert record["model_size"] == [196, 252]  # Pi3 at d = 224 for 640x480 frames
    assert {c["name"].rsplit("-", 1)[0] for c in record["candidates"]} == {"torch-fp32",
                                                                          "torch-bf16"}  # fmt: skip
    assert "within torch bf16's" in record["reason"]
    kind, dtype, threads, why = _resolve_auto(
        BackendKind.AUTO, str(golden_weights), "cpu", None, None, config
    )
    assert (kind.value, dtype.value, threads) == ("torch", chosen["dtype"], chosen["threads"])
    assert why == record["reason"]
    # told otherwise: --dtype / --threads / another device / an explicit backend
    told = _resolve_auto(BackendKind.AUTO, str(golden_weights), "cpu", None, 1, config)
    assert told[:3] == (BackendKind.TORCH, ComputeDtype.FLOAT32, 1)
    explicit = _resolve_auto(BackendKind.ONNX, str(golden_weights), "cpu", None, None, config)
    assert explicit[:3] == (BackendKind.ONNX, ComputeDtype.FLOAT32, None)


def test_tune_refuses_bad_options(golden_weights: Path) -> None:
    for options in (["--runtime", "tensorrt"], ["--seconds", "0"], ["--frame-size", "640"]):
        result = invoke("tune", "--weights", golden_weights, *options)
        assert result.exit_code != 0 and "tune" not in result.stdout

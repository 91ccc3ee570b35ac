"""``eval-many``: the same numbers on every engine, the model loaded once per worker, the table."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from kvtracker_sdk.scale import EvalManyResult, load_manifest, run_many
from tests.scale.manifests import write_manifest


@pytest.fixture(scope="module")
def serial(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, EvalManyResult]:
    folder = tmp_path_factory.mktemp("eval_many")
    manifest = write_manifest(folder)
    return manifest, run_many(load_manifest(manifest), folder / "serial", engine="serial")


def test_one_by_one_scores_every_sequence_and_writes_the_table(
    serial: tuple[Path, EvalManyResult],
) -> None:
    manifest, result = serial
    out = manifest.parent / "serial"
    assert [r.sequence for r in result.results] == [
        "orbit_a", "orbit_b", "orbit_lossy", "tum_head", "tum_noisy", "tum_golden_pi3"
    ]
    assert all(r.error is None and r.ate_rmse_m is not None for r in result.results)
    by_name = {r.sequence: r for r in result.results}
    # 1 cm noise per axis: ATE ~ sqrt(3) cm; 3 cm per axis: about 3x that
    assert by_name["orbit_a"].ate_rmse_m < 0.03 < by_name["tum_noisy"].ate_rmse_m
    assert by_name["orbit_lossy"].valid_poses < by_name["orbit_lossy"].frames  # the loss shows
    assert by_name["tum_golden_pi3"].frames == 20 and not by_name["tum_golden_pi3"].simulated
    document = json.loads((out / "results.json").read_text())
    assert [row["sequence"] for row in document["results"]] == [r.sequence for r in result.results]
    mean = document["averages"]["d224"]["ate_rmse_m"]
    assert mean == pytest.approx(sum(r.ate_rmse_m for r in result.results) / 6, rel=1e-12)
    assert (out / "results.csv").read_text().count("\n") == 7  # header + 6 rows
    assert "| tum_golden_pi3 | d224 | 20 |" in (out / "summary.md").read_text()
    for r in result.results:
        assert (out / r.sequence / "d224" / "trajectory.txt").is_file()
        assert json.loads((out / r.sequence / "d224" / "result.json").read_text())["frames"] == r.frames


def _metrics(result: EvalManyResult) -> list[dict[str, Any]]:
    return result.metrics()


def test_a_local_process_pool_gives_exactly_the_serial_numbers(
    serial: tuple[Path, EvalManyResult],
) -> None:
    manifest, reference = serial
    pooled = run_many(load_manifest(manifest), manifest.parent / "local", engine="local", workers=2)
    assert _metrics(pooled) == _metrics(reference)  # exact: same code, same thread count
    assert len({r.worker for r in pooled.results}) <= 2
    assert max(r.worker_model_loads for r in pooled.results) <= 1  # weights read once per worker


def test_ray_gives_exactly_the_serial_numbers(
    serial: tuple[Path, EvalManyResult], ray_session: Any
) -> None:
    manifest, reference = serial
    distributed = run_many(load_manifest(manifest), manifest.parent / "ray", engine="ray", workers=2)
    assert _metrics(distributed) == _metrics(reference)
    assert max(r.worker_model_loads for r in distributed.results) <= 1
    assert {r.worker for r in distributed.results} != {"main"}  # really ran in the actors


def test_the_cli_runs_a_manifest_and_refuses_a_bad_one(tmp_path: Path) -> None:
    from tests.cli.invoke import invoke

    manifest = tmp_path / "m.json"
    manifest.write_text(json.dumps({"sequences": [
        {"name": "orbit", "simulated": {"orbit_frames": 40, "seed": 9}}]}))
    result = invoke("eval-many", manifest, "--out", tmp_path / "out", "--engine", "serial")
    assert result.exit_code == 0, result.output
    assert "| orbit | default | 40 | 40 |" in result.output
    assert (tmp_path / "out" / "results.csv").is_file()
    manifest.write_text(json.dumps({"sequences": [{"name": "a", "source": "x"}]}))
    result = invoke("eval-many", manifest, "--out", tmp_path / "bad")
    assert result.exit_code == 8 and "real sequences need a model" in result.stderr

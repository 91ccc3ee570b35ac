"""``kvtracker demo`` then ``kvtracker eval``: offline, every output, an ATE that makes sense."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from kvtracker_sdk.io.files.trajectory import read_tum
from tests.cli.invoke import invoke
from tests.helpers import dev_dependency, shared_path

OUTPUTS = {
    "trajectory.txt", "keyframes.json", "points.ply", "run.json", "trajectory.png",
    "groundtruth.txt", "evaluation.json",
}
# 150 frames (5 s) at 30 Hz: the default loss segment is frames 82-127 (55 % + 1.5 s)
DEMO_ARGS = ("--frames", "150", "--size", "90x120", "--resolution", "224")


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("demo")
    result = invoke("demo", "--out", out, *DEMO_ARGS, "--keyframe-interval", "30",
                    "--rerun", out / "demo.rrd")
    assert result.exit_code == 0, result.output
    return out, result.output


def test_demo_writes_every_output(demo_dir: tuple[Path, str]) -> None:
    out, _ = demo_dir
    assert {p.name for p in out.iterdir()} >= OUTPUTS
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]  # atomic writes left nothing
    assert (out / "trajectory.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_demo_is_labelled_simulated_and_walks_the_state_machine(demo_dir: tuple[Path, str]) -> None:
    out, console = demo_dir
    run = json.loads((out / "run.json").read_text())
    assert run["simulated"] is True and "SIMULATED" in run["details"]["notice"]
    assert "SIMULATED" in console
    from rerun.chunk import RrdReader

    recordings = RrdReader(out / "demo.rrd").recordings()
    assert [r.application_id for r in recordings] == ["kvtracker-SIMULATED"]
    assert run["outputs"]["rerun"] == str(out / "demo.rrd")
    assert run["details"]["loss_segment"] == [82, 127]
    # the covered camera is noticed after lost_after (3) frames, recovery after recover_after (3)
    assert run["states_visited"] == ["INIT", "MAPPING", "TRACKING", "RELOCALIZING", "TRACKING"]
    moves = [(c["frame_index"], c["to"], c["reason"]) for c in run["state_changes"]]
    assert (84, "RELOCALIZING", "LOW_CONFIDENCE") in moves
    assert (129, "TRACKING", "RELOCALIZED") in moves
    assert "frame    84: TRACKING -> RELOCALIZING (LOW_CONFIDENCE)" in console
    assert run["frames"] == 150 and run["backend"]["runtime"] == "simulated"
    assert set(run["timings"]) >= {"source", "preprocess", "track", "map", "total"}


def test_demo_outputs_agree_with_each_other(demo_dir: tuple[Path, str]) -> None:
    plyfile = dev_dependency("plyfile")
    out, _ = demo_dir
    run = json.loads((out / "run.json").read_text())
    keyframes = json.loads((out / "keyframes.json").read_text())["keyframes"]
    assert len(keyframes) == run["map"]["keyframes"] >= 3  # bootstrap + one per 30 tracked frames
    # keyframe 0 anchors the world frame; rebuilds correct it by the simulated pass jitter (< 1 mm)
    np.testing.assert_allclose(keyframes[0]["T_world_cam"], np.eye(4), atol=2e-3)
    cloud = plyfile.PlyData.read(str(out / "points.ply"))
    vertices = cloud["vertex"]
    assert len(vertices) == run["map"]["points"] > 1000
    assert np.all(np.asarray(vertices["confidence"]) >= 0.5)  # the confidence filter
    trajectory, truth = read_tum(out / "trajectory.txt"), read_tum(out / "groundtruth.txt")
    assert len(trajectory) == run["valid_poses"] and len(truth) == 150
    # every estimated stamp is one of the ground-truth stamps, bit for bit (full precision)
    assert set(trajectory.stamps.tolist()) <= set(truth.stamps.tolist())


def test_eval_of_the_demo_prints_the_ate_the_noise_predicts(demo_dir: tuple[Path, str]) -> None:
    out, _ = demo_dir
    result = invoke("eval", out / "trajectory.txt", out / "groundtruth.txt", "--json",
                    out / "eval.json", "--plot", out / "eval.png")
    assert result.exit_code == 0, result.output
    match = re.search(r"ATE  RMSE (\d+\.\d+) m", result.stdout)
    assert match is not None, result.stdout
    # 1 cm of noise per axis: sqrt(3) cm expected; keyframe poses and the Sim(3) fit change it
    assert 0.008 < float(match.group(1)) < 0.03
    report = json.loads((out / "eval.json").read_text())
    assert report["ate"]["translation"]["rmse"] == pytest.approx(float(match.group(1)), abs=1e-4)
    assert report["association"]["matched"] == len(read_tum(out / "trajectory.txt"))
    assert (out / "eval.png").is_file()


def test_eval_se3_and_rpe_options(demo_dir: tuple[Path, str]) -> None:
    out, _ = demo_dir
    sim3 = invoke("eval", out / "trajectory.txt", out / "groundtruth.txt", "--no-plot")
    se3 = invoke("eval", out / "trajectory.txt", out / "groundtruth.txt", "--no-plot",
                 "--align", "se3", "--delta", "5", "--all-pairs", "--cm-deg", "2,10")
    assert sim3.exit_code == 0 and se3.exit_code == 0, se3.output
    ate = [float(re.search(r"ATE  RMSE (\d+\.\d+)", r.stdout).group(1)) for r in (sim3, se3)]
    # the simulated world frame has the first mapping pass's random scale: SE(3) cannot fix it
    assert ate[1] > 3 * ate[0]
    assert "delta 5 frames, all pairs" in se3.stdout and "2cm/2deg" in se3.stdout
    assert not (out / "trajectory_eval.png").exists()


def test_demo_over_a_real_tum_ground_truth(tmp_path: Path) -> None:
    gt = shared_path("data", "tum_fr2_desk", "groundtruth.txt")
    result = invoke("demo", "--out", tmp_path, "--gt", gt, "--frames", "60", "--size", "60x80",
                    "--resolution", "224", "--keyframe-interval", "20")
    assert result.exit_code == 0, result.output
    assert {p.name for p in tmp_path.iterdir()} >= OUTPUTS
    truth = read_tum(tmp_path / "groundtruth.txt")
    source = read_tum(gt)
    assert len(truth) == 60 and truth.stamps[0] == source.stamps[0]  # TUM's own clock
    evaluated = invoke("eval", tmp_path / "trajectory.txt", tmp_path / "groundtruth.txt")
    assert evaluated.exit_code == 0, evaluated.output
    assert "ATE  RMSE" in evaluated.stdout
    assert (tmp_path / "trajectory_eval.png").is_file()  # the default plot goes beside EST


def test_object_demo_starts_from_one_box(tmp_path: Path) -> None:
    result = invoke("demo", "--mode", "object", "--out", tmp_path, "--frames", "80", "--loss",
                    "40:55", "--size", "90x120", "--resolution", "224")
    assert result.exit_code == 0, result.output
    document = json.loads((tmp_path / "object.json").read_text())
    frames = document["frames"]
    assert len(frames) == 80 and frames[0]["source"] == "given"
    sources = [f["source"] for f in frames]
    # predicted while tracked; held (T_cam_object null) while the camera is covered (40-55)
    assert sources[1:40] == ["predicted"] * 39 and set(sources[40:55]) == {"held"}
    assert all(f["T_cam_object"] is None for f in frames[40:55])
    assert sources[-1] == "predicted" and frames[-1]["T_cam_object"] is not None
    anchor = document["object_frame"]
    assert anchor is not None and len(anchor["extent"]["half_extents"]) == 3
    run = json.loads((tmp_path / "run.json").read_text())
    assert run["details"]["mode"] == "object" and run["config"]["mode"] == "object"
    assert run["outputs"]["object.json"] == str(tmp_path / "object.json")

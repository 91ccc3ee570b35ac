"""``kvtracker track`` on the real TUM frames with the small golden Pi3 (random weights): every
output, a readable PLY and rerun recording, and a map saved (int8), inspected and relocalised
against."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from kvtracker_sdk.io.files.trajectory import read_tum
from tests.cli.invoke import invoke
from tests.helpers import dev_dependency, shared_path

# tiny model: one thread is as fast and avoids spin-waiting on a shared CI machine
FAST = ("--resolution", "224", "--threads", "1")


@pytest.fixture(scope="module")
def tum() -> Path:
    return shared_path("data", "tum_fr2_desk")


@pytest.fixture(scope="module")
def tracked(tmp_path_factory: pytest.TempPathFactory, tum: Path, golden_weights: Path) -> Path:
    out = tmp_path_factory.mktemp("track")
    result = invoke("track", tum, "--weights", golden_weights, "--out", out, *FAST,
                    "--max-frames", "8", "--keyframe-interval", "3", "--rerun", out / "run.rrd",
                    "--save-map", out / "desk.kvmap", "--cache-dtype", "int8")
    assert result.exit_code == 0, result.output
    return out


def test_track_writes_every_output(tracked: Path, tum: Path) -> None:
    names = {p.name for p in tracked.iterdir()}
    assert {"trajectory.txt", "keyframes.json", "points.ply", "run.json", "trajectory.png",
            "evaluation.json", "run.rrd", "desk.kvmap"} <= names
    run = json.loads((tracked / "run.json").read_text())
    assert run["simulated"] is False and run["backend"]["runtime"] == "torch"
    assert run["frames"] == 8 and run["config"]["resolution"] == 224
    assert run["config"]["keyframing"]["interval_frames"] == 3
    assert len(run["backend"]["fingerprint"]) == 16 and run["versions"]["torch"]
    # the TUM folder ships a ground truth: the run is evaluated against it
    assert run["evaluation"]["association"]["matched"] == run["valid_poses"]
    # stamps are the rgb.txt ones, bit for bit
    listed = [float(line.split()[0]) for line in (tum / "rgb.txt").read_text().splitlines()
              if line and not line.startswith("#")]
    assert read_tum(tracked / "trajectory.txt").stamps.tolist() == listed[: run["valid_poses"]]


def test_points_ply_opens_with_a_standard_reader(tracked: Path) -> None:
    plyfile = dev_dependency("plyfile")
    cloud = plyfile.PlyData.read(str(tracked / "points.ply"))
    vertex = cloud["vertex"]
    names = {p.name for p in vertex.properties}
    assert {"x", "y", "z", "red", "green", "blue", "confidence"} <= names
    run = json.loads((tracked / "run.json").read_text())
    assert len(vertex) == run["map"]["points"]
    xyz = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1)
    assert np.all(np.isfinite(xyz))


def test_rerun_recording_reads_back(tracked: Path) -> None:
    from rerun.chunk import RrdReader

    reader = RrdReader(tracked / "run.rrd")
    assert [r.application_id for r in reader.recordings()] == ["kvtracker"]
    chunks = list(reader.stream())
    entities = {c.entity_path for c in chunks}
    assert {"/world/camera", "/world/camera/image", "/world/points", "/world/trajectory",
            "/world/keyframes/kf_0000", "/world/keyframes/kf_0000/image", "/tracking/state",
            "/tracking/confidence"} <= entities
    frames = set()
    for chunk in chunks:
        if chunk.entity_path == "/world/camera/image":
            frames.update(chunk.to_record_batch().column("frame").to_pylist())
    assert frames == set(range(8))  # one image per frame on the "frame" timeline


def test_map_info_and_relocalising_against_the_saved_map(tracked: Path, tum: Path,
                                                          golden_weights: Path,
                                                          tmp_path: Path) -> None:
    info = invoke("map", "info", tracked / "desk.kvmap", "--json")
    assert info.exit_code == 0, info.output
    facts = json.loads(info.stdout)
    run = json.loads((tracked / "run.json").read_text())
    assert facts["fingerprint"] == run["backend"]["fingerprint"]
    assert facts["keyframes"] == run["map"]["keyframes"] and facts["resolution_hw"] == [196, 252]
    assert facts["preprocessing"] == "pi3-kvtracker-v1"
    assert facts["cache_dtype"] == "int8" and facts["format_version"] == 4  # --cache-dtype int8
    assert facts["keyframe_encoding"] == "compact-xyz"  # Pi3's points: float16 xyz
    text = invoke("map", "info", tracked / "desk.kvmap")
    assert "fingerprint " + facts["fingerprint"] in text.stdout

    again = invoke("track", tum, "--weights", golden_weights, "--out", tmp_path, *FAST,
                   "--start", "8", "--max-frames", "4", "--load-map", tracked / "desk.kvmap")
    assert again.exit_code == 0, again.output
    rerun = json.loads((tmp_path / "run.json").read_text())
    assert rerun["states_visited"][0] == "RELOCALIZING"  # a loaded map is not trusted yet
    assert rerun["state_changes"][0]["reason"] == "RELOCALIZED"
    assert rerun["map"]["keyframes"] >= facts["keyframes"]


def test_object_mode_with_a_mask_folder(tmp_path: Path, tum: Path, golden_weights: Path) -> None:
    masks = tmp_path / "masks"
    masks.mkdir()
    for k in range(3):  # the centre of the 640x480 frames is "the object"
        mask = np.zeros((480, 640), np.uint8)
        mask[120:360, 160:480] = 255
        cv2.imwrite(str(masks / f"{k}.png"), mask)
    out = tmp_path / "out"
    result = invoke("track", tum, "--weights", golden_weights, "--out", out, *FAST,
                    "--mode", "object", "--masks", masks, "--max-frames", "3")
    assert result.exit_code == 0, result.output
    keyframes = json.loads((out / "keyframes.json").read_text())["keyframes"]
    assert keyframes and all(kf["has_mask"] for kf in keyframes)
    assert json.loads((out / "run.json").read_text())["config"]["mode"] == "object"

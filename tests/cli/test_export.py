"""``kvtracker export colmap|nerfstudio`` on the golden-model run over the 20 real TUM frames:
keyframe and all-frame cameras read back by pycolmap, fused points reproject onto their pixels;
the same run's ``--ros2-bag``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from kvtracker_sdk.io.trajectory import read_tum
from tests.cli.invoke import invoke
from tests.helpers import dev_dependency, shared_path
from tests.io.test_colmap_nerfstudio import REPROJECTION_PX, reprojection_errors


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory, golden_weights: Path) -> Path:
    out = tmp_path_factory.mktemp("tum-run")
    result = invoke("-q", "track", shared_path("data", "tum_fr2_desk"), "--weights",
                    golden_weights, "--out", out, "--resolution", "224", "--threads", "1",
                    "--keyframe-interval", "7", "--save-map", out / "desk.kvmap",
                    "--ros2-bag", out / "bag")
    assert result.exit_code == 0, result.output
    return out


def test_colmap_export_of_the_tum_run_reprojects(run: Path, tmp_path: Path) -> None:
    pycolmap = dev_dependency("pycolmap")
    result = invoke("export", "colmap", run, tmp_path, "--all-frames", "--pixel-stride", "3")
    assert result.exit_code == 0, result.output
    model = tmp_path / "sparse" / "0"
    errors = reprojection_errors(model)
    assert len(errors) > 1000 and errors.max() < 1e-6 < REPROJECTION_PX  # exact up to printing
    read = pycolmap.Reconstruction(str(model))
    trajectory = read_tum(run / "trajectory.txt")
    frames = sorted((i for i in read.images.values() if i.name.startswith("frame_")),
                    key=lambda i: i.name)
    assert len(frames) == len(trajectory) == 20
    for image, pose in zip(frames, trajectory.poses, strict=True):
        np.testing.assert_allclose(image.projection_center(), pose[:3, 3], atol=1e-9)
        camera = read.cameras[image.camera_id]
        assert (camera.width, camera.height) == (640, 480)  # the input's frames, not the model's
    keyframes = [i for i in read.images.values() if i.name.startswith("kf_")]
    assert len(keyframes) == json.loads((run / "run.json").read_text())["map"]["keyframes"]


def test_nerfstudio_export_of_the_tum_run(run: Path, tmp_path: Path) -> None:
    result = invoke("export", "nerfstudio", run / "desk.kvmap", tmp_path,
                    "--intrinsics", "520.9086,521.0073,325.1414,249.7018,640,480")
    assert result.exit_code == 0, result.output
    document = json.loads((tmp_path / "transforms.json").read_text())
    scale = document["w"] / 640  # the calibration follows the map's images (model resolution)
    assert document["fl_x"] == pytest.approx(520.9086 * scale, rel=1e-9)


def test_track_writes_a_ros2_bag_of_the_real_frames(run: Path) -> None:
    dev_dependency("rosbags")
    from rosbags.highlevel import AnyReader

    trajectory = read_tum(run / "trajectory.txt")
    with AnyReader([run / "bag"]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        info = next(reader.deserialize(raw, c.msgtype) for c, _, raw in
                    reader.messages([c for c in reader.connections
                                     if c.topic == "/camera/camera_info"]))
        stamps = [t for _, t, _ in reader.messages([c for c in reader.connections
                                                     if c.topic == "/odom"])]
    assert counts["/tf"] == counts["/odom"] == len(trajectory)
    assert (info.width, info.height) == (640, 480)  # the input frames' size
    assert stamps == [round(t * 1e9) for t in trajectory.stamps]

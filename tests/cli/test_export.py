"""``kvtracker export colmap|nerfstudio`` on the golden-model run over the 20 real TUM frames:
keyframe and all-frame cameras read back by pycolmap, fused points reproject onto their pixels;
the same run's ``--ros2-bag``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from kvtracker_sdk.io.files.trajectory import read_tum
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


def _colmap_camera(model: Path) -> tuple[str, list[float], tuple[int, int]]:
    line = next(x for x in (model / "cameras.txt").read_text().splitlines() if x[:1].isdigit())
    _id, kind, width, height, *params = line.split()
    return kind, [float(p) for p in params], (int(width), int(height))


def test_colmap_export_writes_the_camera_stored_in_the_map(run: Path, tmp_path: Path) -> None:
    """The run tracked TUM fr2 with its published camera: the export writes that camera scaled
    to the keyframe images, not a focal fitted to the (random-weight) points."""
    pycolmap = dev_dependency("pycolmap")
    from kvtracker_sdk.io.map_file.map_file import read_map_info

    info = read_map_info(run / "desk.kvmap")
    assert info.camera is not None and info.camera.fx == 520.9  # TUM fr2, stored as given
    height, width = info.resolution
    result = invoke("export", "colmap", run, tmp_path)
    assert result.exit_code == 0, result.output
    model = tmp_path / "sparse" / "0"
    kind, (fx, fy, cx, cy), size = _colmap_camera(model)
    sx, sy = width / 640, height / 480  # the tracker resized the whole (undistorted) frame
    assert kind == "PINHOLE" and size == (width, height)
    # 1e-9: the scaled values written with repr, read back; COLMAP's pixel origin is 0.5 off ours
    assert abs(fx - 520.9 * sx) < 1e-9 and abs(fy - 521.0 * sy) < 1e-9
    assert abs(cx - (325.1 + 0.5) * sx) < 1e-9 and abs(cy - (249.7 + 0.5) * sy) < 1e-9
    camera = next(iter(pycolmap.Reconstruction(str(model)).cameras.values()))
    np.testing.assert_allclose(camera.params, [fx, fy, cx, cy], rtol=0, atol=1e-9)


@pytest.fixture(scope="module")
def uncalibrated_run(tmp_path_factory: pytest.TempPathFactory, golden_weights: Path) -> Path:
    """The golden (random-weight) model over three TUM frames given as a plain image folder:
    no camera is known, and the tracker's fitted focal is implausible."""
    folder = tmp_path_factory.mktemp("frames")
    for index, image in enumerate(sorted((shared_path("data", "tum_fr2_desk") / "rgb").iterdir())[:3]):
        (folder / f"{index}.png").symlink_to(image)  # linked, never copied
    out = tmp_path_factory.mktemp("uncalibrated")
    result = invoke("-q", "track", folder, "--weights", golden_weights, "--out", out,
                    "--resolution", "224", "--threads", "1", "--keyframe-interval", "1",
                    "--save-map", out / "map.kvmap")
    assert result.exit_code == 0, result.output
    return out


def test_without_a_camera_an_implausible_fit_is_refused_saying_how_to_pass_one(
    uncalibrated_run: Path, tmp_path: Path
) -> None:
    result = invoke("export", "colmap", uncalibrated_run, tmp_path / "refused")
    assert result.exit_code != 0
    assert "IntrinsicsError" in result.stderr or "focal" in result.stderr
    assert "--camera FILE" in result.stderr and "--intrinsics fx,fy,cx,cy,W,H" in result.stderr
    assert not (tmp_path / "refused" / "sparse").exists()  # nothing half-written
    forced = invoke("export", "colmap", uncalibrated_run, tmp_path / "forced", "--force-fitted-focal")
    assert forced.exit_code == 0, forced.output
    _kind, (fx, *_rest), (width, _height) = _colmap_camera(tmp_path / "forced" / "sparse" / "0")
    assert fx < width / 10
    camera_file = tmp_path / "camera.json"
    camera_file.write_text(json.dumps({"fx": 520.9, "fy": 521.0, "cx": 325.1, "cy": 249.7,
                                       "width": 640, "height": 480}))
    given = invoke("export", "colmap", uncalibrated_run, tmp_path / "given", "--camera", camera_file)
    assert given.exit_code == 0, given.output
    _kind, (fx, *_rest), (width, _height) = _colmap_camera(tmp_path / "given" / "sparse" / "0")
    assert abs(fx - 520.9 * width / 640) < 1e-9

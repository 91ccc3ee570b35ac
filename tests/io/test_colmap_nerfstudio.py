"""COLMAP and nerfstudio export, read back by pycolmap: fused points reproject onto their pixels
(< 1 px; in fact ~1e-9), poses and pixel conventions survive, nerfstudio cameras look where the
poses look. On a simulated map (through the API) and on a demo run (through the CLI)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.errors import InputError
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.io.exports.colmap_text import write_colmap_text
from kvtracker_sdk.io.exports.intrinsics import estimate_intrinsics
from kvtracker_sdk.io.exports.nerfstudio import write_nerfstudio
from kvtracker_sdk.io.exports.reconstruction import Reconstruction, reconstruction_from_map
from tests.cli.invoke import invoke
from tests.helpers import dev_dependency
from tests.tracking.sim_session import SIZE, drive, make_tracker

REPROJECTION_PX = 1.0  # the bound; the export is exact up to float formatting


def reprojection_errors(model: Path) -> np.ndarray:
    """Pixel distance between each COLMAP point projected into its images and its 2D point."""
    pycolmap = dev_dependency("pycolmap")
    reconstruction = pycolmap.Reconstruction(str(model))
    errors = []
    for point in reconstruction.points3D.values():
        for element in point.track.elements:
            image = reconstruction.images[element.image_id]
            camera = reconstruction.cameras[image.camera_id]
            projected = camera.img_from_cam(image.cam_from_world() * point.xyz)
            errors.append(np.linalg.norm(projected - image.points2D[element.point2D_idx].xy))
    return np.asarray(errors)


@pytest.fixture(scope="module")
def simulated() -> tuple[Any, Reconstruction]:
    backend = SimulatedBackend(orbit(num_frames=60, turns=0.25), seed=1)
    with make_tracker(backend, keyframing={"interval_frames": 20}) as tracker:
        drive(tracker, backend, stop=41)
        keyframe_map = tracker.keyframe_map
    return keyframe_map, reconstruction_from_map(keyframe_map, stride=4)


def test_colmap_model_reads_back_with_poses_and_reprojects(
    simulated: tuple[Any, Reconstruction], tmp_path: Path
) -> None:
    pycolmap = dev_dependency("pycolmap")
    keyframe_map, reconstruction = simulated
    model = write_colmap_text(reconstruction, tmp_path)
    errors = reprojection_errors(model)
    assert len(errors) == len(reconstruction.points) > 1000
    assert errors.max() < 1e-6 < REPROJECTION_PX
    read = pycolmap.Reconstruction(str(model))
    assert len(read.cameras) == 1 and len(read.images) == keyframe_map.num_keyframes
    camera = read.cameras[1]
    assert (camera.width, camera.height) == (SIZE[1], SIZE[0])
    # COLMAP's pixel centres sit at +0.5: the image centre is W/2, not (W-1)/2
    assert (camera.principal_point_x, camera.principal_point_y) == (SIZE[1] / 2, SIZE[0] / 2)
    for image in read.images.values():
        kf = keyframe_map.keyframe(int(image.name[3:7]))
        np.testing.assert_allclose(image.projection_center(), kf.T_world_cam[:3, 3], atol=1e-9)
        np.testing.assert_allclose(image.viewing_direction(), kf.T_world_cam[:3, 2], atol=1e-9)
        written = cv2.imread(str(tmp_path / "images" / image.name))[..., ::-1]
        np.testing.assert_array_equal(written, kf.image)


def test_points_lie_at_the_model_depth_on_their_rays(simulated: tuple[Any, Reconstruction]) -> None:
    keyframe_map, reconstruction = simulated
    first = reconstruction.point_image == 0
    kf = keyframe_map.keyframes[0]
    u, v = reconstruction.point_uv[first].astype(int).T
    T_cam_world = np.linalg.inv(kf.T_world_cam)
    in_camera = reconstruction.points[first] @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    np.testing.assert_allclose(in_camera[:, 2], kf.local_points[v, u, 2], rtol=1e-6)
    assert reconstruction.pinhole_residual_px < 0.01  # the simulated points are a pinhole's


def test_nerfstudio_cameras_look_along_the_poses(
    simulated: tuple[Any, Reconstruction], tmp_path: Path
) -> None:
    keyframe_map, reconstruction = simulated
    document = json.loads(write_nerfstudio(reconstruction, tmp_path).read_text())
    assert document["ply_file_path"] == "points.ply" and (tmp_path / "points.ply").is_file()
    camera = reconstruction.images[0].intrinsics
    assert (document["cx"], document["cy"]) == (camera.cx + 0.5, camera.cy + 0.5)
    assert (document["w"], document["h"]) == (SIZE[1], SIZE[0])
    for frame, kf in zip(document["frames"], keyframe_map.keyframes, strict=True):
        assert (tmp_path / frame["file_path"]).is_file()
        c2w = np.array(frame["transform_matrix"])
        # OpenGL camera: looks along -z, y up; the SDK's (OpenCV): looks along +z, y down
        np.testing.assert_allclose(-c2w[:3, 2], kf.T_world_cam[:3, 2], atol=1e-12)
        np.testing.assert_allclose(-c2w[:3, 1], kf.T_world_cam[:3, 1], atol=1e-12)
        np.testing.assert_allclose(c2w[:3, 3], kf.T_world_cam[:3, 3], atol=1e-12)


def test_intrinsics_estimate_and_resize() -> None:
    truth = Camera(200.0, 200.0, 125.5, 90.5, 252, 182)
    depth = np.random.default_rng(0).uniform(1.0, 3.0, (182, 252, 1))
    points = truth.rays() * depth
    fitted = estimate_intrinsics(points)
    assert fitted.fx == pytest.approx(200.0, rel=1e-9) and (fitted.cx, fitted.cy) == (125.5, 90.5)
    doubled = truth.resized(504, 364)  # pixel centres: c' = 2 c + 0.5
    assert (doubled.fx, doubled.cx, doubled.cy) == (400.0, 251.5, 181.5)
    with pytest.raises(InputError):
        Camera(-1.0, 1.0, 0.0, 0.0, 10, 10)


def test_demo_run_exports_through_the_cli(tmp_path: Path) -> None:
    run = tmp_path / "run"
    result = invoke("-q", "demo", "--out", run, "--frames", "45", "--no-loss", "--size", "120x160",
                    "--keyframe-interval", "20", "--save-map", run / "map.kvmap")
    assert result.exit_code == 0, result.output
    result = invoke("export", "colmap", run, tmp_path / "colmap", "--pixel-stride", "4")
    assert result.exit_code == 0, result.output
    errors = reprojection_errors(tmp_path / "colmap" / "sparse" / "0")
    assert len(errors) > 1000 and errors.max() < 1e-6 < REPROJECTION_PX  # exact up to printing
    result = invoke("export", "nerfstudio", run / "map.kvmap", tmp_path / "ns")
    assert result.exit_code == 0, result.output
    assert len(json.loads((tmp_path / "ns" / "transforms.json").read_text())["frames"]) == 3
    result = invoke("export", "colmap", run, tmp_path / "all", "--all-frames")
    assert result.exit_code == 3 and "track" in result.output  # a simulated run has no frames
    with pytest.raises(InputError, match="exactly one"):
        from kvtracker_sdk.io.exports.run_reconstruction import find_map
        find_map(tmp_path)

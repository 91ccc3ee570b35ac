"""``Camera``: intrinsics through resizes and crops, the OpenGL projection, undistortion."""

from __future__ import annotations

import numpy as np
import pytest

from kvtracker_sdk.errors import InputError
from kvtracker_sdk.geometry.camera import Camera, gl_view_matrix
from kvtracker_sdk.geometry.pixel_transform import PixelTransform
from kvtracker_sdk.preprocess.undistort import Undistorter

TUM_FR2 = Camera(520.9, 521.0, 325.1, 249.7, 640, 480, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172))


def test_k_and_dict_round_trip_bit_exact() -> None:
    camera = Camera(520.9086, 521.0073, 325.1414, 249.7018, 640, 480, (0.1, -0.2, 0.0, 0.0, 0.3))
    np.testing.assert_array_equal(
        camera.K(), [[520.9086, 0, 325.1414], [0, 521.0073, 249.7018], [0, 0, 1]]
    )
    assert Camera.from_dict(camera.to_dict()) == camera
    assert Camera.from_K(camera.K(), 640, 480, camera.distortion) == camera
    assert camera.size == (480, 640) and camera.has_distortion
    assert Camera(1, 1, 0, 0, 2, 2, (0, 0, 0, 0)).distortion == ()  # all-zero: none


@pytest.mark.parametrize(
    "kwargs",
    [{"fx": 0.0}, {"fy": float("nan")}, {"width": 0}, {"distortion": (0.1, 0.2)}],
)
def test_bad_cameras_are_refused(kwargs: dict[str, object]) -> None:
    values: dict[str, object] = {"fx": 500.0, "fy": 500.0, "cx": 320.0, "cy": 240.0,
                                 "width": 640, "height": 480}
    values.update(kwargs)
    with pytest.raises(InputError):
        Camera(**values)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="skew"):
        Camera.from_K(np.array([[500.0, 3.0, 320.0], [0, 500, 240], [0, 0, 1]]), 640, 480)


@pytest.mark.parametrize("seed", range(5))
def test_a_3d_point_projects_to_the_same_place_through_resize_and_crop(seed: int) -> None:
    """Property: project, then transform the pixel == transform K, then project (1e-9)."""
    rng = np.random.default_rng(seed)
    height, width = (int(v) for v in rng.integers(50, 900, size=2))
    camera = Camera(*rng.uniform(100, 900, 2), *rng.uniform(0, 1, 2) * [width, height], width, height)
    x0, y0 = (int(v) for v in rng.integers(0, 40, size=2))
    crop_hw = (height - y0 - int(rng.integers(0, 10)), width - x0 - int(rng.integers(0, 10)))
    out_hw = (int(rng.integers(14, 600)), int(rng.integers(14, 600)))
    transform = PixelTransform.crop(x0, y0).then(PixelTransform.resize(crop_hw, out_hw))
    points = rng.uniform([-2, -2, 0.3], [2, 2, 9], size=(100, 3))
    resized = camera.transformed(transform, out_hw)
    assert resized.size == out_hw
    np.testing.assert_allclose(
        resized.project(points), transform.apply(camera.project(points)), rtol=0, atol=1e-9
    )
    back = resized.transformed(transform.inverse(), camera.size)
    np.testing.assert_allclose(back.K(), camera.K(), rtol=1e-12)


def test_resize_maps_the_image_edges_exactly() -> None:
    # a half-size resize: the left edge -0.5 stays the edge -0.5, the centre stays the centre
    camera = Camera(500.0, 500.0, 319.5, 239.5, 640, 480)
    half = camera.transformed(PixelTransform.resize((480, 640), (240, 320)), (240, 320))
    assert (half.fx, half.fy, half.cx, half.cy) == (250.0, 250.0, 159.5, 119.5)
    with pytest.raises(InputError, match="undistort"):
        TUM_FR2.transformed(PixelTransform.identity(), (480, 640))


def test_projection_matrix_hand_derived_case() -> None:
    """640x480, f = 500, centred principal point, near 0.1, far 10: the glFrustum matrix with
    l, r = ∓0.1·320/500, b, t = ∓0.1·240/500, i.e. P00 = 2n/(r-l) = 500/320 = 1.5625,
    P11 = 500/240, P22 = -(f+n)/(f-n) = -10.1/9.9, P23 = -2fn/(f-n) = -2/9.9, P32 = -1."""
    camera = Camera(500.0, 500.0, 319.5, 239.5, 640, 480)
    expected = np.array([
        [1.5625, 0.0, 0.0, 0.0],
        [0.0, 500.0 / 240.0, 0.0, 0.0],
        [0.0, 0.0, -10.1 / 9.9, -2.0 / 9.9],
        [0.0, 0.0, -1.0, 0.0],
    ])  # fmt: skip
    np.testing.assert_allclose(camera.projection_matrix(0.1, 10.0), expected, rtol=0, atol=1e-12)


def test_projection_matrix_maps_pixels_to_ndc() -> None:
    """Off-centre principal point: the point seen at pixel (u, v) lands at NDC
    x = 2(u + 0.5)/W - 1, y = 1 - 2(v + 0.5)/H, depth -1 at near and +1 at far."""
    camera = Camera(480.0, 510.0, 300.25, 260.75, 640, 480)
    near, far = 0.2, 20.0
    projection = camera.projection_matrix(near, far)
    T_world_cam = np.eye(4)
    T_world_cam[:3, 3] = [0.3, -0.1, 0.5]
    view = gl_view_matrix(T_world_cam)
    for (u, v), depth in [((-0.5, -0.5), near), ((639.5, 479.5), far), ((100.0, 400.0), 3.0)]:
        ray = np.array([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0])
        world = np.append(ray * depth + T_world_cam[:3, 3], 1.0)  # the camera is not rotated
        clip = projection @ view @ world
        ndc = clip[:3] / clip[3]
        expected_z = -1.0 if depth == near else (1.0 if depth == far else ndc[2])
        np.testing.assert_allclose(
            ndc, [2 * (u + 0.5) / 640 - 1, 1 - 2 * (v + 0.5) / 480, expected_z], atol=1e-12
        )
    with pytest.raises(InputError):
        camera.projection_matrix(1.0, 0.5)


def test_undistortion_straightens_what_the_lens_bent() -> None:
    """A point seen through the TUM fr2 lens (cv2.projectPoints) lands, after undistortion, at
    its pinhole projection with the same K (within a pixel: bilinear remap of a blob)."""
    import cv2

    camera = TUM_FR2
    point = np.array([[0.35, -0.25, 1.0]])
    distorted_uv = cv2.projectPoints(
        point, np.zeros(3), np.zeros(3), camera.K(), np.array(camera.distortion)
    )[0].reshape(2)
    image = np.zeros((480, 640, 3), np.uint8)
    cv2.circle(image, (int(round(distorted_uv[0])), int(round(distorted_uv[1]))), 3,
               (255, 255, 255), -1)
    straight = Undistorter()(image, camera)
    assert straight.shape == image.shape
    rows, cols = np.nonzero(straight[..., 0] > 64)
    found = np.array([cols.mean(), rows.mean()])
    expected = camera.undistorted().project(point)[0]
    assert np.linalg.norm(found - expected) < 1.5
    assert np.linalg.norm(distorted_uv - expected) > 5  # the lens moved it noticeably
    assert Undistorter()(image, camera.undistorted()) is image
    with pytest.raises(InputError, match="does not match"):
        Undistorter()(image[:10], camera)


def test_pinhole_intrinsics_is_a_deprecated_name_of_camera() -> None:
    import kvtracker_sdk
    from kvtracker_sdk.io.exports import intrinsics

    with pytest.warns(DeprecationWarning, match="use kvtracker_sdk.Camera"):
        old = intrinsics.PinholeIntrinsics
    assert old is Camera
    assert "PinholeIntrinsics" not in kvtracker_sdk.__all__  # the root holds the app's names only


def test_resized_keeps_the_lens_and_scales_k_exactly() -> None:
    camera = Camera(520.9, 521.0, 325.1, 249.7, 640, 480, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172))
    half = camera.resized(320, 240)
    assert half.distortion == camera.distortion and half.size == (240, 320)
    # pixel centres at integers: u' = (u + 0.5) / 2 - 0.5
    assert (half.fx, half.cx) == (camera.fx / 2, (camera.cx + 0.5) / 2 - 0.5)
    rays = half.rays()
    assert rays.shape == (240, 320, 3)
    np.testing.assert_allclose(half.project(rays[7, 11][None]), [[11.0, 7.0]], atol=1e-12)

"""Intrinsics out of the tracker: given, predicted by DA3 (golden), estimated from local points."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from safetensors.numpy import load_file

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import GroundTruth, orbit
from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.geometry.camera import Camera, IntrinsicsSource
from kvtracker_sdk.tracking.core.intrinsics import fit_intrinsics
from kvtracker_sdk.tracking.core.model_input import FramePreparer
from kvtracker_sdk.tracking.facade.tracker import Tracker
from tests.helpers import shared_path

SIZE = (240, 320)  # the rendered frames; the tracker resizes them to 224x294 at resolution 308


@pytest.fixture(scope="module")
def ground_truth() -> GroundTruth:
    return orbit(40, radius=1.5)


def test_fit_recovers_a_pinhole_camera_from_its_points() -> None:
    rng = np.random.default_rng(0)
    K = np.array([[410.0, 0, 151.3], [0, 395.5, 98.7], [0, 0, 1]])
    height, width = 190, 260
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    depth = rng.uniform(0.5, 4.0, size=(2, height, width))
    rays = np.stack(((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)), -1)
    points = (rays * depth[..., None]).astype(np.float32)  # float32, like a network's output
    fit = fit_intrinsics(points, rng.uniform(0.1, 1.0, size=(2, height, width)))
    assert fit is not None and fit.num_points == 2 * height * width
    np.testing.assert_allclose(fit.K, K, rtol=1e-5)
    assert fit.rms_px < 1e-3
    sampled = fit_intrinsics(points[:, ::3, ::3], pixel_step=3)  # every 3rd pixel, full-res K
    assert sampled is not None
    np.testing.assert_allclose(sampled.K, K, rtol=1e-5)
    noisy = points * rng.normal(1.0, 0.01, size=points.shape).astype(np.float32)
    fit_noisy = fit_intrinsics(noisy)
    assert fit_noisy is not None and 0.5 < fit_noisy.rms_px < 10  # the error says how good
    flat = np.zeros((1, 8, 8, 3), np.float32)
    flat[..., 2] = 1.0  # every ray parallel: no perspective, no fit
    assert fit_intrinsics(flat) is None


def test_the_simulated_cameras_focal_is_recovered(ground_truth: GroundTruth) -> None:
    """Estimated (Pi3-like backend, no intrinsics head) through FrameResult: fx = fy = 0.81 W."""
    backend = SimulatedBackend(ground_truth, camera_size=SIZE, seed=1)
    with Tracker(TrackerConfig(), backend) as tracker:
        results = [tracker.push_frame(f.image, timestamp=f.timestamp)
                   for f in backend.frames(SIZE, stop=6)]
    truth = Camera(0.81 * 320, 0.81 * 320, 159.5, 119.5, 320, 240)
    for result in results:
        camera = result.intrinsics
        assert camera is not None and result.intrinsics_source is IntrinsicsSource.ESTIMATED
        assert camera.size == SIZE  # the input image's, not the model's 224x294
        assert camera.fx == pytest.approx(truth.fx, rel=0.01)
        assert camera.fy == pytest.approx(truth.fy, rel=0.01)
        assert (camera.cx, camera.cy) == pytest.approx((truth.cx, truth.cy), abs=0.01 * 320)


def test_given_intrinsics_pass_through_undistorted(ground_truth: GroundTruth) -> None:
    backend = SimulatedBackend(ground_truth, camera_size=SIZE, seed=1)
    session = Camera(260.0, 261.0, 160.2, 119.1, 320, 240, (0.1, -0.05, 0.0, 0.0))
    per_frame = Camera(250.0, 250.0, 159.5, 119.5, 320, 240)
    frames = list(backend.frames(SIZE, stop=3))
    with Tracker(TrackerConfig(), backend, camera=session) as tracker:
        first = tracker.push_frame(frames[0].image, timestamp=frames[0].timestamp)
        second = tracker.push_frame(frames[1].image, camera=per_frame)
        tracker.camera = None
        third = tracker.push_frame(frames[2].image)
    assert first.intrinsics == session.undistorted()  # the frame was undistorted first
    assert first.intrinsics_source is IntrinsicsSource.GIVEN
    assert second.intrinsics == per_frame and second.intrinsics_source is IntrinsicsSource.GIVEN
    assert third.intrinsics_source is IntrinsicsSource.ESTIMATED


def test_da3_golden_intrinsics_through_the_backend_and_the_tracker() -> None:
    """The official DA3 ``intrinsics`` (golden, reduced model) come out of the SDK's public
    outputs: the backend's MapResult / TrackResult (float inputs, rtol 1e-5), and FrameResult
    carries TrackResult's K to the input image through the inverse resize (exact)."""
    torch_backend = pytest.importorskip("kvtracker_sdk.backends.torch_backend")
    golden = shared_path("golden", "da3")
    backend = torch_backend.TorchBackend.from_pretrained(golden / "weights.safetensors")
    images = load_file(str(golden / "inputs.safetensors"))["imgs_01"][0].transpose(0, 2, 3, 1)
    expected = load_file(str(golden / "outputs_query.safetensors"))
    mapped = backend.map(np.ascontiguousarray(images[:3]))
    assert mapped.intrinsics is not None
    np.testing.assert_allclose(mapped.intrinsics, expected["keyframes.intrinsics"][0], rtol=1e-5)
    tracked = backend.track(np.ascontiguousarray(images[3]), mapped.cache)
    assert tracked.intrinsics is not None
    np.testing.assert_allclose(tracked.intrinsics, expected["query.intrinsics"][0, 0], rtol=1e-5)

    # through the tracker: uint8 frames of another size; FrameResult carries the backend's K of
    # the model image back to the pushed image through the inverse of the frame's transform
    frames = [np.round(cv2.resize(i, (504, 364)) * 255).astype(np.uint8) for i in images]
    with Tracker(TrackerConfig(resolution=224), backend) as tracker:
        results = [tracker.push_frame(frame) for frame in frames]
        kf_map, config = tracker.keyframe_map, tracker.config
    assert kf_map is not None and kf_map.generation == 1  # no rebuild after frame 0
    result = results[1]  # a tracked frame (frame 0 made the map)
    assert result.intrinsics_source is IntrinsicsSource.PREDICTED and result.intrinsics is not None
    assert result.intrinsics.size == (364, 504)
    prepared = FramePreparer(config, patch_size=14, family="da3").prepare(frames[1])
    assert prepared.image.shape[:2] != (364, 504)  # the model saw a resized frame
    own = backend.track(prepared.image, kf_map.cache)  # the same pass as the tracker's
    assert own.intrinsics is not None
    np.testing.assert_allclose(
        result.intrinsics.K(), prepared.transform.inverse().apply_to_K(own.intrinsics), rtol=1e-12
    )

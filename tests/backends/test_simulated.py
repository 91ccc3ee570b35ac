"""SimulatedBackend: the Backend contract from a ground-truth trajectory."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from kvtracker_sdk.backends.base import Backend
from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import (
    GroundTruth,
    decode_frame_index,
    encode_frame_index,
    orbit,
)
from kvtracker_sdk.errors import BackendError, CacheError, TrajectoryError
from kvtracker_sdk.geometry.se3 import check_rigid
from kvtracker_sdk.geometry.sim3 import umeyama_alignment
from kvtracker_sdk.types import HeadSet

SIZE = (182, 252)


@pytest.fixture(scope="module")
def backend() -> SimulatedBackend:
    return SimulatedBackend(
        orbit(200), translation_noise_m=0.0, rotation_noise_deg=0.0, pass_jitter=0.0
    )


def _images(backend: SimulatedBackend, indices: list[int]) -> np.ndarray:
    camera = backend.camera(SIZE, textured=False)
    return np.stack([camera.render(i).image for i in indices])


def test_implements_the_backend_protocol(backend: SimulatedBackend) -> None:
    assert isinstance(backend, Backend)
    info = backend.info
    assert (info.backend, info.family, info.patch_size) == ("simulated", "simulated", 14)
    same = SimulatedBackend(
        orbit(200), translation_noise_m=0.0, rotation_noise_deg=0.0, pass_jitter=0.0
    )
    other = SimulatedBackend(orbit(200), seed=1)
    assert same.info.fingerprint == info.fingerprint  # same function
    assert other.info.fingerprint != info.fingerprint


@pytest.mark.parametrize("index", [0, 1, 223, 224, 3000, 20956])
def test_frame_code_survives_resizing_masking_and_cropping(index: int) -> None:
    red, green = encode_frame_index(index)
    image = np.zeros((480, 640, 3), dtype=np.uint8)
    image[..., 0], image[..., 1], image[..., 2] = red, green, 90
    assert decode_frame_index(cv2.resize(image, (252, 182), interpolation=cv2.INTER_AREA)) == index
    assert decode_frame_index(cv2.resize(image, (700, 518), interpolation=cv2.INTER_CUBIC)) == index
    masked = image.copy()
    masked[:, :600] = 0  # a small object in a black background: the grid misses it
    assert decode_frame_index(masked) == index
    assert decode_frame_index(image[200:260, 300:380]) == index


def test_images_without_a_code_are_refused() -> None:
    rng = np.random.default_rng(0)
    with pytest.raises(BackendError, match="SimulatedCamera"):
        decode_frame_index(rng.integers(0, 256, size=(64, 64, 3), dtype=np.uint8))
    with pytest.raises(BackendError):
        decode_frame_index(np.zeros((64, 64, 3), dtype=np.uint8))


def test_each_pass_lives_in_its_own_random_sim3_frame(backend: SimulatedBackend) -> None:
    """Noise off: a pass's poses equal the ground truth up to one Sim(3), different per pass."""
    indices = [0, 20, 40, 60, 80]
    gt = backend.ground_truth.poses[indices]
    gauges = []
    for _ in range(2):
        result = backend.map(_images(backend, indices))
        assert result.poses.shape == (5, 4, 4) and all(check_rigid(p) for p in result.poses)
        align = umeyama_alignment(result.poses[:, :3, 3], gt[:, :3, 3])
        np.testing.assert_allclose(align.apply_to_pose(result.poses), gt, atol=1e-9)
        gauges.append(align)
    assert abs(np.log(gauges[0].scale / gauges[1].scale)) > 1e-3


def test_map_outputs_have_contract_shapes_and_consistent_depth(backend: SimulatedBackend) -> None:
    result = backend.map(_images(backend, [0, 50]))
    assert result.confidence.shape == (2, *SIZE) and result.confidence.dtype == np.float32
    assert result.local_points.shape == (2, *SIZE, 3)
    assert result.confidence.min() > 0.0 and result.confidence.max() <= 1.0
    assert not result.poses.flags.writeable
    cache = result.cache
    assert cache.num_keyframes == 2 and cache.keyframe_ids == (0, 1)
    assert cache.tokens_per_frame == backend.info.tokens_per_frame(*SIZE)
    hidden, frames = backend.read_cache(cache)
    assert frames == (0, 50)
    # raw depth = true depth x the pass's scale: the sphere at the orbit centre is 1.5 m - 0.3 m
    # ahead along the optical axis (orbit radius 1.5, height 0.4, sphere radius 0.3)
    centre_depth = result.local_points[0, SIZE[0] // 2, SIZE[1] // 2, 2] / hidden.scale
    assert centre_depth == pytest.approx(np.hypot(1.5, 0.4) - 0.3, abs=2e-3)


def test_track_returns_the_pose_in_the_cache_frame(backend: SimulatedBackend) -> None:
    result = backend.map(_images(backend, [0, 50]))
    hidden, _ = backend.read_cache(result.cache)
    tracked = backend.track(_images(backend, [123])[0], result.cache)
    np.testing.assert_allclose(
        tracked.pose, hidden.apply_to_pose(backend.ground_truth.poses[123]), atol=1e-9
    )
    assert tracked.confidence is not None and tracked.confidence_map is not None
    fast = backend.track(_images(backend, [123])[0], result.cache, heads=HeadSet.CAMERA)
    assert fast.confidence is None and fast.confidence_map is None
    full = backend.track(_images(backend, [123])[0], result.cache, heads=HeadSet.ALL)
    assert full.local_points is not None and full.local_points.shape == (*SIZE, 3)


def test_noise_is_fixed_per_frame_plus_pass_jitter() -> None:
    noisy = SimulatedBackend(orbit(100), translation_noise_m=0.01, pass_jitter=0.0, seed=3)
    images = _images(noisy, [10, 30, 50])
    first, second = noisy.map(images), noisy.map(images)
    # different hidden frames, same per-frame errors: aligned, the two passes agree exactly
    align = umeyama_alignment(first.poses[:, :3, 3], second.poses[:, :3, 3])
    np.testing.assert_allclose(align.apply_to_pose(first.poses), second.poses, atol=1e-9)
    truth = noisy.ground_truth.poses[[10, 30, 50], :3, 3]
    to_truth = umeyama_alignment(first.poses[:, :3, 3], truth, with_scale=True)
    assert np.abs(to_truth.apply_to_points(first.poses[:, :3, 3]) - truth).max() > 1e-4


def test_confidence_drops_over_loss_segments_and_map_only_drops() -> None:
    sim = SimulatedBackend(orbit(100), loss_segments=[(40, 45)], map_confidence_drops=[(60, 61)])
    result = sim.map(_images(sim, [0, 42, 60]))
    levels = result.confidence.mean(axis=(1, 2))
    assert levels[1] < 0.2 * levels[0] and levels[2] < 0.2 * levels[0]
    tracked = [
        sim.track(_images(sim, [i])[0], result.cache).confidence for i in (39, 40, 44, 45, 60)
    ]
    assert tracked[1] < 0.2 * tracked[0] and tracked[2] < 0.2 * tracked[0]
    assert tracked[3] == pytest.approx(tracked[0]) and tracked[4] == pytest.approx(tracked[0])


def test_foreign_caches_and_bad_images_are_refused(backend: SimulatedBackend) -> None:
    from kvtracker_sdk.cache.kv_cache import CacheLayout, KVCache

    foreign = KVCache(CacheLayout((0,), 2, 8), 10)
    with pytest.raises(CacheError):
        backend.read_cache(foreign)
    with pytest.raises(BackendError):
        backend.map(np.zeros((2, 182, 252), dtype=np.uint8))


def test_from_tum_resamples_the_real_trajectory_to_30_hz(tum_dir: Path) -> None:
    gt = GroundTruth.from_tum(tum_dir / "groundtruth.txt")
    assert 2950 < len(gt) < 3000  # ~99.4 s at 30 Hz
    steps = np.diff(gt.timestamps)
    assert np.median(steps) == pytest.approx(1 / 30, abs=2e-3)
    assert all(check_rigid(p, atol=1e-5) for p in gt.poses[::100])
    full = GroundTruth.from_tum(tum_dir / "groundtruth.txt", rate_hz=None)
    assert len(full) == 20957


def test_from_tum_reports_malformed_files(tmp_path: Path) -> None:
    bad = tmp_path / "gt.txt"
    bad.write_text("# t x y z\n1 2 3\n")
    with pytest.raises(TrajectoryError):
        GroundTruth.from_tum(bad)
    with pytest.raises(TrajectoryError):
        GroundTruth.from_tum(tmp_path / "missing.txt")


def test_frames_generator_renders_textured_frames_with_masks(backend: SimulatedBackend) -> None:
    frames = list(backend.frames(size=(120, 160), stop=3, with_mask=True))
    assert [f.index for f in frames] == [0, 1, 2]
    first = frames[0]
    assert first.image.shape == (120, 160, 3) and first.mask is not None and first.mask.any()
    assert first.image[..., 2].std() > 5  # a visible texture
    assert decode_frame_index(first.image) == 0
    np.testing.assert_array_equal(first.T_world_cam, backend.ground_truth.poses[0])


def test_frames_of_another_trajectory_are_refused() -> None:
    short = SimulatedBackend(orbit(10))
    longer_frame = SimulatedBackend(orbit(50)).camera(SIZE, textured=False).render(30).image
    with pytest.raises(BackendError, match="10 frames"):
        short.map(longer_frame[None])

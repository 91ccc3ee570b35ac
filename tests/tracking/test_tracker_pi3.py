"""End to end with the real Pi3 port (the small golden weights) over the 20 real TUM frames."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from kvtracker_sdk.tracking.facade.tracker import Tracker
from kvtracker_sdk.types import TrackingState
from tests.helpers import shared_path

torch_backend = pytest.importorskip("kvtracker_sdk.backends.torch_backend")


@pytest.fixture(scope="module")
def frames() -> list[tuple[float, np.ndarray]]:
    folder = shared_path("data", "tum_fr2_desk", "rgb")
    files = sorted(folder.glob("*.png"))
    assert len(files) == 20
    return [(float(f.stem), cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB)) for f in files]


@pytest.fixture(scope="module")
def weights() -> Path:
    return shared_path("golden", "pi3", "weights.safetensors")


@pytest.mark.slow
def test_real_frames_run_end_to_end(frames: list[tuple[float, np.ndarray]], weights: Path) -> None:
    moves: list[tuple[str, str, str]] = []
    with Tracker.from_pretrained(
        weights, resolution=224, keyframing={"interval_frames": 5}
    ) as tracker:
        tracker.events.on_state_change(
            lambda e: moves.append((e.previous.value, e.state.value, e.reason.value))
        )
        results = [tracker.push_frame(image, timestamp=stamp) for stamp, image in frames]
        status = tracker.map_status
        cache = tracker.keyframe_map.cache
        backend = tracker.backend
    assert moves[:2] == [("INIT", "MAPPING", "BOOTSTRAP"), ("MAPPING", "TRACKING", "BOOTSTRAP")]
    assert results[0].state is TrackingState.TRACKING and results[0].keyframe_id == 0
    # exact on any CPU: the first keyframe's camera is the world frame by definition (computed
    # from the network's float32 pose it was the identity to ~1e-6, differently per ISA)
    np.testing.assert_array_equal(results[0].pose.T_world_cam, np.eye(4))
    # random small weights give arbitrary but well-formed outputs: every frame yields a rigid pose
    assert all(r.pose is not None and r.pose.is_rigid(atol=1e-4) for r in results)
    assert [r.frame_index for r in results if r.is_keyframe] == [0, 5, 10, 15]
    assert status.keyframe_ids == (0, 1, 2, 3) and cache.keyframe_ids == (0, 1, 2, 3)
    assert cache.tokens_per_frame == backend.info.tokens_per_frame(196, 252)  # 640x480 at 224
    assert all(0.0 <= r.confidence <= 1.0 for r in results)
    assert [r.timestamp for r in results] == [stamp for stamp, _ in frames]


@pytest.mark.slow
def test_swap_to_a_bf16_backend_converts_the_cache(
    frames: list[tuple[float, np.ndarray]], weights: Path
) -> None:
    import torch

    with Tracker.from_pretrained(weights, resolution=224) as tracker:
        for stamp, image in frames[:3]:
            tracker.push_frame(image, timestamp=stamp)
        fp32_pose = tracker.push_frame(frames[3][1]).pose
        bf16 = torch_backend.TorchBackend.from_pretrained(weights, dtype=torch.bfloat16)
        assert bf16.info.fingerprint == tracker.backend.info.fingerprint  # same weights
        previous = tracker.set_backend(bf16)
        assert tracker.keyframe_map.cache.dtype == torch.bfloat16
        bf16_pose = tracker.push_frame(frames[3][1]).pose
        previous.close()
        bf16.close()
    # bf16 rounding (8 bits of mantissa) moves the pose a little, not wholesale
    assert bf16_pose is not None and fp32_pose is not None
    assert np.abs(bf16_pose.translation - fp32_pose.translation).max() < 0.1

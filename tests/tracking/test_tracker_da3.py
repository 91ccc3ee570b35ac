"""End to end with the real Depth Anything 3 port (the small golden weights) over real TUM frames.

The twin of ``test_tracker_pi3.py`` for the second family: ``Tracker.from_pretrained`` picks DA3
from the checkpoint, keyframe 0 defines the world frame, and a saved map refuses a Pi3 backend.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from kvtracker_sdk.errors import MapModelMismatchError
from kvtracker_sdk.io.map_file.map_file import read_map_info
from kvtracker_sdk.tracking.facade.tracker import Tracker
from kvtracker_sdk.types import TrackingState
from tests.helpers import shared_path

torch_backend = pytest.importorskip("kvtracker_sdk.backends.torch_backend")


@pytest.fixture(scope="module")
def frames() -> list[tuple[float, np.ndarray]]:
    files = sorted(shared_path("data", "tum_fr2_desk", "rgb").glob("*.png"))[:12]
    return [(float(f.stem), cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB)) for f in files]


@pytest.mark.slow
def test_da3_end_to_end_and_map_family(
    frames: list[tuple[float, np.ndarray]], tmp_path: Path
) -> None:
    weights = shared_path("golden", "da3", "weights.safetensors")
    with Tracker.from_pretrained(
        weights, resolution=224, keyframing={"interval_frames": 5}
    ) as tracker:
        results = [tracker.push_frame(image, timestamp=stamp) for stamp, image in frames]
        info = tracker.backend.info
        cache = tracker.keyframe_map.cache  # type: ignore[union-attr]
        tracker.save_map(tmp_path / "desk.kvmap")
    assert (info.family, info.model) == ("da3", "da3-custom")
    assert results[0].state is TrackingState.TRACKING and results[0].keyframe_id == 0
    # exact on any CPU: the first keyframe's camera is the world frame by definition
    np.testing.assert_array_equal(results[0].pose.T_world_cam, np.eye(4))  # type: ignore[union-attr]
    assert all(r.pose is not None and r.pose.is_rigid(atol=1e-4) for r in results)
    assert [r.frame_index for r in results if r.is_keyframe] == [0, 5, 10]
    # DA3's own sizing: 224 is the longest side, 640x480 -> 168x224 (12 x 16 patches + camera)
    assert cache.tokens_per_frame == info.tokens_per_frame(168, 224) == 1 + 12 * 16
    assert read_map_info(tmp_path / "desk.kvmap").preprocessing == "da3-upper-bound-v1"
    assert all(0.0 <= r.confidence <= 1.0 for r in results)

    pi3 = torch_backend.TorchBackend.from_pretrained(
        shared_path("golden", "pi3", "weights.safetensors")
    )
    with pytest.raises(MapModelMismatchError, match="family"):
        Tracker.from_map(tmp_path / "desk.kvmap", pi3)

"""Object mode from one box with the real networks (the small golden Pi3 and DA3 weights) on the
20 real TUM fr2/desk frames: the session runs end to end and every frame gets a region.

The golden weights are random, so their geometry is arbitrary: the region may be predicted from
it, or held when the projection leaves the image; what must hold is the plumbing (intrinsics
estimated for Pi3, predicted for DA3, regions on every frame, no exception).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.tracking.facade.tracker import Tracker
from kvtracker_sdk.types import RegionSource
from tests.helpers import shared_path

pytest.importorskip("kvtracker_sdk.backends.torch_backend")

BOX = (200.0, 150.0, 440.0, 330.0)  # the middle of the desk in the 640x480 frames


@pytest.fixture(scope="module")
def frames() -> list[tuple[float, np.ndarray]]:
    files = sorted(shared_path("data", "tum_fr2_desk", "rgb").glob("*.png"))
    assert len(files) == 20
    return [(float(f.stem), cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB)) for f in files]


@pytest.mark.slow
@pytest.mark.parametrize("family", ["pi3", "da3"])
def test_one_box_gives_every_real_frame_a_region(
    family: str, frames: list[tuple[float, np.ndarray]]
) -> None:
    weights = shared_path("golden", family, "weights.safetensors")
    with Tracker.from_pretrained(weights, mode="object", resolution=224) as tracker:
        if family == "pi3":  # random Pi3 points fit no pinhole: give the published intrinsics
            tracker.camera = Camera(520.9, 521.0, 325.1, 249.7, 640, 480)
        results = [
            tracker.push_frame(image, timestamp=stamp, bbox=BOX if i == 0 else None)
            for i, (stamp, image) in enumerate(frames)
        ]
        object_frame = tracker.object.frame
    assert len(results) == 20 and all(r.region is not None for r in results)
    assert results[0].region.source is RegionSource.GIVEN and results[0].region.box == BOX
    assert {r.region.source for r in results[1:]} <= {RegionSource.PREDICTED, RegionSource.HELD}
    for result in results:
        x0, y0, x1, y1 = result.region.box
        assert 0 <= x0 < x1 <= 640 and 0 <= y0 < y1 <= 480
        assert result.region.mask.shape == (480, 640) and result.region.mask.any()
    assert object_frame is not None and np.isfinite(object_frame.T_world_object).all()
    # a frame is predicted only where a pose and intrinsics exist, held where the projection of
    # the random networks' points leaves the image; both kinds occur
    assert any(r.region.source is RegionSource.PREDICTED for r in results)
    assert all(r.pose_valid and r.intrinsics is not None for r in results
               if r.region.source is RegionSource.PREDICTED)

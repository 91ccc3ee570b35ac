"""The object as the map knows it (fused foreground points, frame, extent) and its projection."""

from __future__ import annotations

import numpy as np
import pytest

from kvtracker_sdk.backends.simulated_scene import (
    SimulatedScene,
    camera_matrix,
    look_at,
    pixel_rays,
)
from kvtracker_sdk.cache.keyframe_map import Keyframe
from kvtracker_sdk.geometry.boxes import box_iou, mask_box
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.preprocess import box_mask
from kvtracker_sdk.tracking.object.object_model import foreground_points, voxel_subsample
from kvtracker_sdk.tracking.object.object_region import grown_mask, project_region, region_of_mask
from kvtracker_sdk.types import RegionSource

SIZE = (120, 160)
SCENE = SimulatedScene(np.full(3, -4.0), np.full(3, 4.0), np.zeros(3), 0.3)


def _view(azimuth_deg: float) -> np.ndarray:
    a = np.radians(azimuth_deg)
    return look_at(np.array([1.5 * np.cos(a), 1.5 * np.sin(a), 0.3]), np.zeros(3),
                   np.array([0.0, 0.0, 1.0]))


def _keyframe(pose: np.ndarray, mask: np.ndarray) -> Keyframe:
    rays = pixel_rays(SIZE)
    depth, _ = SCENE.depth(pose, rays)
    return Keyframe(0, 0, None, np.zeros((*SIZE, 3), np.uint8), mask, pose,
                    np.ones(SIZE, np.float32), (rays * depth[..., None]).astype(np.float32), 1.0)


def test_a_box_keeps_the_object_and_drops_the_far_background() -> None:
    pose = _view(0.0)
    box = SCENE.object_box(pose, SIZE)
    assert box is not None
    x0, y0, x1, y1 = box
    loose = (x0 - 10, y0 - 10, x1 + 10, y1 + 10)  # a sloppy tap: background in every corner
    points = foreground_points(_keyframe(pose, box_mask(loose, SIZE)), step=1)
    distance = np.linalg.norm(points - SCENE.object_centre, axis=1)
    assert distance.max() < 0.3 + 1e-3  # all on the sphere: the walls (>= 2.5 m) are gone
    _, on_object = SCENE.depth(pose, pixel_rays(SIZE))
    assert len(points) == on_object.sum()  # and every object pixel kept


def test_projected_region_matches_the_silhouette_from_another_view() -> None:
    keyframes = [_keyframe(_view(a), np.ones(SIZE, bool)) for a in (0.0, 20.0, 40.0)]
    points = np.concatenate([foreground_points(kf, step=1) for kf in keyframes])
    points = points[np.linalg.norm(points, axis=1) < 0.31]
    camera = Camera.from_K(camera_matrix(SIZE), SIZE[1], SIZE[0])
    pose = _view(30.0)
    region = project_region(voxel_subsample(points, 4096), pose, camera, margin=50, frame_index=3)
    assert region is not None and region.source is RegionSource.PREDICTED
    truth = SCENE.object_box(pose, SIZE)
    assert truth is not None and box_iou(region.box, truth) > 0.95
    _, silhouette = SCENE.depth(pose, pixel_rays(SIZE))
    mask = region.mask
    assert (mask & silhouette).sum() / (mask | silhouette).sum() > 0.9  # mask IoU
    assert region.context_box == (max(0.0, region.box[0] - 50), max(0.0, region.box[1] - 50),
                                  min(160.0, region.box[2] + 50), min(120.0, region.box[3] + 50))
    # looking away: out of view
    away = look_at(np.array([1.5, 0.0, 0.3]), np.array([3.0, 0.0, 0.3]), np.array([0.0, 0.0, 1.0]))
    assert project_region(points, away, camera, margin=50, frame_index=4) is None


def test_region_masks_round_trip_and_grow_within_the_context_box() -> None:
    mask = np.zeros(SIZE, dtype=bool)
    mask[40:60, 50:90] = True
    mask[50, 60] = False
    region = region_of_mask(mask, None, margin=5, frame_index=0, source=RegionSource.GIVEN)
    assert region.box == mask_box(mask) and np.array_equal(region.mask, mask)
    assert region.mask_bits.nbytes <= 20 * 40 // 8 + 1  # the packed crop, not the image
    grown = grown_mask(region)
    assert mask_box(grown) == (45.0, 35.0, 95.0, 65.0)  # 6 px of growth, cut at the 5 px context
    assert region.held().source is RegionSource.HELD and region.held().frame_index == 0


@pytest.mark.parametrize("limit", [100, 1000])
def test_voxel_subsample_keeps_sparse_regions(limit: int) -> None:
    rng = np.random.default_rng(3)
    dense = rng.normal(scale=0.01, size=(20000, 3))
    sparse = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    kept = voxel_subsample(np.concatenate([dense, sparse]), limit)
    assert len(kept) <= limit
    assert {tuple(p) for p in sparse} <= {tuple(p) for p in kept}  # an even subsample drops them

"""Masks and object boxes follow the image: same resize, the paper's dilation in input pixels."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.preprocess import for_family
from kvtracker_sdk.tracking.core.model_input import FramePreparer

H, W = 480, 640


def test_pi3_masks_are_bilinear_then_any() -> None:
    mask = np.zeros((H, W), dtype=bool)
    mask[100:103, 200:203] = True  # 3 x 3 pixels: kept wherever a bilinear sample touches them
    size = for_family("pi3").model_size((H, W), 224, 14)
    ours = for_family("pi3").resize_mask(mask, size)
    expected = cv2.resize(mask.astype(np.float32), size[::-1], interpolation=cv2.INTER_LINEAR) > 0
    np.testing.assert_array_equal(ours, expected)
    assert ours.any() and ours.dtype == bool


@pytest.mark.parametrize("family", ["pi3", "da3"])
def test_mask_and_image_share_one_geometry(family: str) -> None:
    """An image of the mask and the mask land on the same pixels (to the filters' blur)."""
    mask = np.zeros((H, W), dtype=bool)
    mask[120:360, 160:480] = True
    image = np.repeat(mask[..., None].astype(np.uint8) * 255, 3, axis=2)
    pipeline = for_family(family)
    resized = pipeline.resize(image, 224, 14)
    small = pipeline.resize_mask(mask, resized.size)
    inside = resized.image[..., 0] > 127
    assert np.mean(inside != small) < 0.02  # only a one-pixel rim may differ (any vs 1/2)
    x0, y0 = resized.transform.apply(np.array([160.0 - 0.5, 120.0 - 0.5]))  # the mask's corner
    columns = np.flatnonzero(small.any(axis=0))
    rows = np.flatnonzero(small.any(axis=1))
    assert abs(columns[0] - (x0 + 0.5)) <= 1 and abs(rows[0] - (y0 + 0.5)) <= 1


def _object_frame(margin: int, **config: object) -> tuple[np.ndarray, object]:
    image = np.zeros((H, W, 3), dtype=np.uint8)
    image[200:260, 300:340] = 255  # a 40 x 60 object
    preparer = FramePreparer(
        TrackerConfig(
            resolution=224,
            mode="object",
            object={"preprocessing": "crop", "crop_margin_px": margin},
            **config,
        ),
        patch_size=14,
        family="pi3",
    )
    return image, preparer


@pytest.mark.parametrize("margin", [50, 0])
def test_crop_dilates_the_box_by_the_margin_in_input_pixels(margin: int) -> None:
    image, preparer = _object_frame(margin)
    box = (300.0, 200.0, 340.0, 260.0)
    frame = preparer.prepare(image, bbox=box)  # type: ignore[attr-defined]
    # the crop window, read back through the transform: model pixels -> input pixels
    back = frame.transform.inverse()
    h, w = frame.image.shape[:2]
    # pixel edges (centres at integers): the window's outer edges, in input pixel-edge units
    left, top = back.apply(np.array([-0.5, -0.5])) + 0.5
    right, bottom = back.apply(np.array([w - 0.5, h - 0.5])) + 0.5
    # the box dilated by the margin fits inside the window, which is at most one pixel larger
    # than the dilated box along its limiting side (the other grows to the model's aspect)
    assert left <= 300 - margin + 1e-9 and right >= 340 + margin - 1e-9
    assert top <= 200 - margin + 1e-9 and bottom >= 260 + margin - 1e-9
    assert min(right - left - (40 + 2 * margin), bottom - top - (60 + 2 * margin)) <= 1 + 1e-9
    # the box's pixels are where the transform says
    u0, v0 = frame.transform.apply(np.array([300.0, 200.0]))
    u1, v1 = frame.transform.apply(np.array([339.0, 259.0]))
    assert frame.image[int(round((v0 + v1) / 2)), int(round((u0 + u1) / 2)), 0] == 255
    assert frame.mask is not None and frame.mask.shape == frame.image.shape[:2]


def test_bbox_mask_mode_goes_through_the_image_resize() -> None:
    image = np.full((H, W, 3), 200, dtype=np.uint8)
    preparer = FramePreparer(
        TrackerConfig(resolution=224, mode="object"), patch_size=14, family="pi3"
    )
    box = (160.0, 120.0, 480.0, 360.0)
    frame = preparer.prepare(image, bbox=box)
    full = np.zeros((H, W), dtype=bool)
    full[120:360, 160:480] = True
    expected = for_family("pi3").resize_mask(full, frame.image.shape[:2])
    np.testing.assert_array_equal(frame.mask, expected)
    assert np.all(frame.image[~expected] == 0) and np.all(frame.image[expected] == 200)

"""Frame validation (typed errors) and preprocessing to model resolution (object mask / crop)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.errors import (
    BBoxError,
    ImageDtypeError,
    ImageShapeError,
    InputError,
    MaskError,
    NonFiniteImageError,
    ResolutionChangedError,
)
from kvtracker_sdk.preprocess import fit_box
from kvtracker_sdk.tracking.core.model_input import FramePreparer, resolve_resolution

H, W = 240, 320  # 4:3 input -> 196 x 252 at d = 224 (Pi3, as KV-Tracker)
MODEL = (196, 252)


def _preparer(**config: object) -> FramePreparer:
    return FramePreparer(TrackerConfig(resolution=224, **config), patch_size=14, family="pi3")


def _image(value: int = 100) -> np.ndarray:
    return np.full((H, W, 3), value, dtype=np.uint8)


def test_uint8_is_resized_to_model_resolution_and_never_aliases_the_input() -> None:
    image = _image()
    frame = _preparer().prepare(image, timestamp=1.5)
    assert frame.image.shape == (*MODEL, 3) and frame.image.dtype == np.uint8
    assert frame.input_size == (H, W) and frame.timestamp == 1.5 and frame.mask is None
    same_size = np.full((*MODEL, 3), 7, dtype=np.uint8)
    prepared = _preparer().prepare(same_size).image
    assert not np.shares_memory(prepared, same_size)  # keyframes freeze their copy, not the user's


def test_float_images_in_unit_range_are_accepted_and_rounded() -> None:
    image = np.full((*MODEL, 3), 128 / 255, dtype=np.float32)
    assert np.all(_preparer().prepare(image).image == 128)
    assert _preparer().prepare(image.astype(np.float16)).image.dtype == np.uint8


@pytest.mark.parametrize(
    ("image", "error"),
    [
        ([[0, 0, 0]], ImageDtypeError),
        (np.zeros((H, W), np.uint8), ImageShapeError),
        (np.zeros((H, W, 4), np.uint8), ImageShapeError),
        (np.zeros((3, H, W), np.uint8), ImageShapeError),
        (np.zeros((10, W, 3), np.uint8), ImageShapeError),  # smaller than a patch
        (np.zeros((H, W, 3), np.int16), ImageDtypeError),
        (np.zeros((H, W, 3), bool), ImageDtypeError),
        (np.full((H, W, 3), 1.5, np.float32), ImageDtypeError),
        (np.full((H, W, 3), -0.1, np.float64), ImageDtypeError),
        (np.full((H, W, 3), np.nan, np.float32), NonFiniteImageError),
        (np.full((H, W, 3), np.inf, np.float64), NonFiniteImageError),
    ],
)
def test_bad_images_raise_typed_errors(image: object, error: type[InputError]) -> None:
    with pytest.raises(error):
        _preparer().prepare(image)


@pytest.mark.parametrize(
    ("mask", "error"),
    [
        (np.zeros((H, W), bool), MaskError),  # selects nothing
        (np.ones((H, W - 1), bool), MaskError),
        (np.ones((H, W), np.float32), MaskError),
        ("everything", MaskError),
    ],
)
def test_bad_masks_raise_mask_error(mask: object, error: type[InputError]) -> None:
    with pytest.raises(error):
        _preparer().prepare(_image(), mask=mask)


def test_tiny_mask_that_vanishes_at_model_resolution_is_refused() -> None:
    mask = np.zeros((960, 1280), dtype=np.uint8)
    # bilinear at x0.204 (rows) / x0.197 (columns) reads rows (1, 2), (6, 7), ... and columns
    # (2, 3), (7, 8), ...: pixel (4, 4) touches no sample
    mask[4, 4] = 255
    with pytest.raises(MaskError, match="too small"):
        _preparer().prepare(np.zeros((960, 1280, 3), np.uint8), mask=mask)


@pytest.mark.parametrize(
    "bbox",
    [(10, 10, 5, 20), (0, 0, W + 1, 10), (-1, 0, 10, 10), (0, 0, 10), (0, 0, np.nan, 10), "box"],
)
def test_bad_boxes_raise_bbox_error(bbox: object) -> None:
    with pytest.raises(BBoxError):
        _preparer().prepare(_image(), bbox=bbox)


@pytest.mark.parametrize("timestamp", [float("nan"), float("inf"), "noon"])
def test_bad_timestamps_raise_input_error(timestamp: object) -> None:
    with pytest.raises(InputError, match="timestamp"):
        _preparer().prepare(_image(), timestamp=timestamp)


def test_resolution_changes_are_refused() -> None:
    with pytest.raises(ResolutionChangedError, match="reset"):
        _preparer().prepare(_image(), session_input_size=(480, 640))
    with pytest.raises(ResolutionChangedError, match="map"):
        _preparer().prepare(_image(), map_resolution=(266, 350))


def test_object_mode_needs_a_mask_or_a_box() -> None:
    with pytest.raises(MaskError, match="object mode"):
        _preparer(mode="object").prepare(_image())


def test_object_mask_mode_blacks_out_the_background() -> None:
    mask = np.zeros((H, W), dtype=bool)
    mask[60:180, 80:240] = True
    frame = _preparer(mode="object").prepare(_image(200), mask=mask)
    assert frame.mask is not None and frame.mask.shape == MODEL
    assert np.all(frame.image[frame.mask] == 200)
    assert np.all(frame.image[~frame.mask] == 0)
    box_frame = _preparer(mode="object").prepare(_image(200), bbox=(80, 60, 240, 180))
    np.testing.assert_array_equal(box_frame.mask, frame.mask)  # a box is a rectangular mask


def test_object_crop_mode_crops_around_the_box_dilated_and_at_model_aspect() -> None:
    image = np.zeros((H, W, 3), dtype=np.uint8)
    image[100:140, 140:180] = 255  # a 40 x 40 white object
    mask = image[..., 0] > 0
    frame = _preparer(
        mode="object", object={"preprocessing": "crop", "crop_margin_px": 20}
    ).prepare(image, mask=mask)
    assert frame.image.shape == (*MODEL, 3)
    # crop: 80 px wide box grown to 196:252 -> ~103 x 80 px: the object spans ~40/103 of the width
    white_columns = np.flatnonzero(frame.image[98, :, 0] > 127)
    assert 0.3 < len(white_columns) / 252 < 0.45
    assert frame.mask is not None and frame.mask[98, 126]  # the object is centred


@settings(max_examples=200, deadline=None)
@given(
    x0=st.floats(0, W - 2),
    y0=st.floats(0, H - 2),
    w=st.floats(1, W),
    h=st.floats(1, H),
    margin=st.integers(0, 80),
)
def test_crop_window_stays_inside_and_contains_the_box(
    x0: float, y0: float, w: float, h: float, margin: int
) -> None:
    box = (x0, y0, min(x0 + w, W), min(y0 + h, H))
    left, top, right, bottom = fit_box(box, (H, W), margin=margin, aspect=196 / 252)
    assert 0 <= left < right <= W and 0 <= top < bottom <= H
    # the box (dilated, when the image allows) lies inside the window
    assert left <= max(box[0] - margin, 0) + 1 and right >= min(box[2] + margin, W) - 1
    assert top <= max(box[1] - margin, 0) + 1 and bottom >= min(box[3] + margin, H) - 1
    if right - left < W and bottom - top < H:  # not clipped: the model's aspect, up to whole pixels
        rounding = 2.0 / (right - left) + 2.0 / (bottom - top)
        assert (bottom - top) / (right - left) == pytest.approx(196 / 252, abs=0.01 + rounding)


@pytest.mark.parametrize(
    ("family", "side", "size"),
    [("pi3", 308, (266, 350)), ("simulated", 308, (266, 350)), ("da3", 504, (378, 504))],
)
def test_an_unset_resolution_is_the_familys_default(
    family: str, side: int, size: tuple[int, int]
) -> None:
    assert resolve_resolution(TrackerConfig(), family).resolution == side
    assert resolve_resolution(TrackerConfig(resolution=224), family).resolution == 224
    preparer = FramePreparer(TrackerConfig(), patch_size=14, family=family)
    assert preparer.prepare(np.zeros((480, 640, 3), np.uint8)).image.shape[:2] == size

"""The prepared frame's PixelTransform is where preprocessing really moved the pixels: a bright
spot of the input image lands where the transform says, after a resize and after a crop."""

from __future__ import annotations

import numpy as np
import pytest

from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.tracking.core.model_input import FramePreparer


def _spot_image(u: float, v: float, size: tuple[int, int] = (240, 320)) -> np.ndarray:
    """A Gaussian spot (sigma 4 px) centred at pixel coordinates (u, v), pixel centres at
    integers."""
    rows, cols = np.mgrid[0 : size[0], 0 : size[1]].astype(np.float64)
    spot = np.exp(-((cols - u) ** 2 + (rows - v) ** 2) / (2 * 4.0**2))
    return np.repeat((spot * 255).round().astype(np.uint8)[..., None], 3, axis=2)


def _centroid(image: np.ndarray) -> np.ndarray:
    weight = image[..., 0].astype(np.float64)
    rows, cols = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    return np.array([(weight * cols).sum(), (weight * rows).sum()]) / weight.sum()


@pytest.mark.parametrize("family", ["pi3", "da3"])
@pytest.mark.parametrize(
    "config, bbox",
    [
        (TrackerConfig(resolution=224), None),  # 240x320 -> 182x252: an anisotropic resize
        (TrackerConfig(resolution=518), None),  # upsampling
        (TrackerConfig(mode="object", resolution=224, object={"preprocessing": "crop",
                                                              "crop_margin_px": 8}),
         (150.0, 100.0, 260.0, 200.0)),  # crop, then resize
    ],
)
def test_a_spot_lands_where_the_transform_says(
    config: TrackerConfig, bbox: tuple[float, float, float, float] | None, family: str
) -> None:
    u, v = 203.3, 151.7
    preparer = FramePreparer(config, patch_size=14, family=family)
    prepared = preparer.prepare(_spot_image(u, v), bbox=bbox)
    expected = prepared.transform.apply(np.array([u, v]))
    if bbox is not None:
        assert prepared.transform.ox < 0  # a crop really happened
    # 0.02 px (measured <= 0.009): a half-pixel slip in the resize map (>= 0.1 px here) fails
    assert np.abs(_centroid(prepared.image) - expected).max() < 0.02

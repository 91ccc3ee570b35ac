"""PixelTransform follows cv2.resize and crops exactly (pixel-centre convention)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from kvtracker_sdk.errors import InputError
from kvtracker_sdk.geometry.pixel_transform import PixelTransform


def test_resize_transform_maps_a_single_bright_pixel_where_cv2_linear_puts_it() -> None:
    # Upsampling 2x with bilinear: the source pixel centre (3, 2) lands at 2*3 + 0.5 = 6.5.
    image = np.zeros((8, 8), np.float32)
    image[2, 3] = 1.0
    resized = cv2.resize(image, (16, 16), interpolation=cv2.INTER_LINEAR)
    ys, xs = np.nonzero(resized)
    centroid = np.array([(xs * resized[ys, xs]).sum(), (ys * resized[ys, xs]).sum()])
    centroid /= resized[ys, xs].sum()
    mapped = PixelTransform.resize((8, 8), (16, 16)).apply(np.array([3.0, 2.0]))
    np.testing.assert_allclose(centroid, mapped, atol=1e-6)


def test_projection_is_preserved_through_resize_then_crop() -> None:
    rng = np.random.default_rng(0)
    K = np.array([[520.9, 0, 325.1], [0, 521.0, 249.7], [0, 0, 1.0]])
    points = rng.uniform([-1, -1, 1], [1, 1, 4], size=(50, 3))
    uv = (points @ K.T)[:, :2] / points[:, 2:]
    transform = PixelTransform.resize((480, 640), (196, 252)).then(PixelTransform.crop(7, 3))
    K2 = transform.apply_to_K(K)
    uv2 = (points @ K2.T)[:, :2] / points[:, 2:]
    np.testing.assert_allclose(uv2, transform.apply(uv), rtol=0, atol=1e-9)
    np.testing.assert_allclose(transform.inverse().apply(uv2), uv, rtol=0, atol=1e-9)


@pytest.mark.parametrize("bad", [dict(sx=0.0), dict(sy=-1.0), dict(ox=float("nan"))])
def test_degenerate_transforms_are_refused(bad: dict[str, float]) -> None:
    with pytest.raises(InputError):
        PixelTransform(**bad)

"""The transform returned with every resize is the exact pixel map of what OpenCV did."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.preprocess import for_family
from kvtracker_sdk.preprocess.resampling import resample
from kvtracker_sdk.tracking.core.model_input import FramePreparer

K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])


def _project(K: np.ndarray, points: np.ndarray) -> np.ndarray:
    uvw = points @ K.T
    return uvw[:, :2] / uvw[:, 2:]


@pytest.mark.parametrize("family", ["pi3", "da3"])
@pytest.mark.parametrize("crop", [False, True])
def test_projected_points_follow_the_transform(family: str, crop: bool) -> None:
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(-1, 1, (50, 2)), rng.uniform(1, 4, 50)])
    mode = {"mode": "object", "object": {"preprocessing": "crop"}} if crop else {}
    preparer = FramePreparer(TrackerConfig(resolution=224, **mode), patch_size=14, family=family)
    frame = preparer.prepare(
        np.zeros((480, 640, 3), np.uint8), bbox=(250, 180, 330, 300) if crop else None
    )
    K_model = frame.transform.apply_to_K(K)  # the intrinsics of the prepared image
    np.testing.assert_allclose(
        _project(K_model, points), frame.transform.apply(_project(K, points)), rtol=0, atol=1e-9
    )


@pytest.mark.parametrize(("family", "source"), [("pi3", (480, 640)), ("da3", (480, 640)),
                                                 ("da3", (259, 601)), ("pi3", (640, 480))])
@pytest.mark.parametrize("side", [224, 308, 518])
def test_resampled_coordinates_equal_the_transform(
    family: str, source: tuple[int, int], side: int
) -> None:
    """Resample images whose values are their own x (and y) coordinates: each output pixel then
    holds the source position it was sampled at, which the inverse transform must give (away
    from the replicated border). Bilinear reproduces a ramp exactly (Pi3: 1e-9 px); OpenCV's area
    filter at non-integer ratios and its cubic (a = -0.75) do not quite, by a zero-mean ripple
    (one step: 0.017 and 0.048 px measured; DA3's two steps compound to 0.16 source px), so DA3's
    plans are held to 0.2 source px, and their mean offset to 0.01 px (a wrong transform, e.g.
    a half-pixel slip, would be off by a constant)."""
    height, width = source
    pipeline = for_family(family)
    plan = pipeline.plan(source, side, 14)
    transform = pipeline.resize(np.zeros((*source, 3), np.uint8), side, 14).transform
    xs, ys = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    sampled = np.stack([resample(xs, plan), resample(ys, plan)], axis=-1)
    out_h, out_w = sampled.shape[:2]
    u, v = np.meshgrid(np.arange(out_w, dtype=np.float64), np.arange(out_h, dtype=np.float64))
    expected = transform.inverse().apply(np.stack([u, v], axis=-1))
    interior = (slice(6, out_h - 6), slice(6, out_w - 6))
    error = sampled[interior] - expected[interior]
    exact = all(step.interpolation == cv2.INTER_LINEAR for step in plan)
    assert np.abs(error).max() <= (1e-9 if exact else 0.2)
    assert np.abs(error.mean(axis=(0, 1))).max() <= (1e-9 if exact else 0.01)

"""The metric scale of a mapping pass from sensor depth at its keyframes.

Estimator: the **confidence-weighted median of the log ratios** ``log(sensor depth / predicted
depth)`` over every pixel valid in both, across all keyframes that have a depth frame. Why this
one and not a least-squares fit or IRLS:

* a depth sensor's noise grows with depth (about proportional to it for stereo and structured
  light), so the error of a ratio is multiplicative: symmetric in log space, not in linear;
* the outliers are not Gaussian: flying pixels at depth edges, black or shiny surfaces, a few
  pixels of mis-registration, the network's blurred depth at occlusion boundaries. A median
  ignores up to half of the samples being wrong without a threshold to tune (IRLS needs an
  inlier scale and a start; a mean follows the outliers);
* the network's confidence weights each pixel by how much its predicted depth can be trusted.

Uncertainty (1-sigma, relative): ``1.2533 * 1.4826 * MAD / sqrt(n_eff)``, the standard error of a
median of samples whose robust spread is ``1.4826 * MAD`` (weighted MAD of the log ratios).
``n_eff`` counts model patches, not pixels: a network predicts depth per patch token, so the
errors of one patch's pixels are correlated and would make a per-pixel count far too confident.
A calibration error of the sensor's own depth scale is not observable here and not included.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["DepthScaleFit", "fit_depth_scale", "weighted_median"]

_MEDIAN_SE = 1.2533  # sqrt(pi / 2): standard error of a median / of a mean, Gaussian samples
_MAD_TO_SIGMA = 1.4826  # MAD of a Gaussian times this is its standard deviation
_STRIDE = 2  # every 2nd pixel per axis: neighbours are correlated, a quarter of the sort cost


@dataclass(frozen=True)
class DepthScaleFit:
    """Metres per unit of the predicted depth, with its relative 1-sigma uncertainty."""

    scale: float
    relative_uncertainty: float
    pixels: int  # valid pixels used
    patches: int  # distinct model patches among them (n_eff)


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The value where the cumulative weight of the sorted ``values`` reaches half the total."""
    order = np.argsort(values, kind="stable")
    cumulative = np.cumsum(weights[order], dtype=np.float64)
    index = int(np.searchsorted(cumulative, 0.5 * cumulative[-1]))
    return float(values[order][min(index, len(values) - 1)])


def fit_depth_scale(
    sensor_depths: Sequence[np.ndarray | None],
    predicted_depths: Sequence[np.ndarray],
    confidences: Sequence[np.ndarray],
    masks: Sequence[np.ndarray | None],
    *,
    patch_size: int,
    min_pixels: int = 64,
) -> DepthScaleFit | None:
    """Fit ``sensor ≈ scale * predicted`` over the keyframes (see the module docstring).

    Per keyframe: ``sensor_depths`` float32 [h, w] metres (0 = invalid; None: no depth frame),
    ``predicted_depths`` [h, w] (a mapping pass's local point z), ``confidences`` [h, w] in
    [0, 1], ``masks`` bool [h, w] or None (object mode: only the object's pixels). None when
    fewer than ``min_pixels`` pixels are valid in both.
    """
    logs, weights, patch_ids = [], [], []
    for index, (sensor, predicted, confidence, mask) in enumerate(
        zip(sensor_depths, predicted_depths, confidences, masks, strict=True)
    ):
        if sensor is None:
            continue
        s = np.asarray(sensor[::_STRIDE, ::_STRIDE], dtype=np.float64)
        p = np.asarray(predicted[::_STRIDE, ::_STRIDE], dtype=np.float64)
        w = np.asarray(confidence[::_STRIDE, ::_STRIDE], dtype=np.float64)
        valid = (s > 0) & (p > 0) & np.isfinite(s) & np.isfinite(p) & (w > 0)
        if mask is not None:
            valid &= mask[::_STRIDE, ::_STRIDE]
        if not valid.any():
            continue
        rows, cols = np.nonzero(valid)
        logs.append(np.log(s[valid]) - np.log(p[valid]))
        weights.append(w[valid])
        # the patch of each sample (strided coordinates back to model pixels)
        per_row = predicted.shape[1] // patch_size + 1
        patch_ids.append(
            index * 10**9 + (rows * _STRIDE // patch_size) * per_row + cols * _STRIDE // patch_size
        )
    if not logs:
        return None
    log_ratio, weight = np.concatenate(logs), np.concatenate(weights)
    if len(log_ratio) < min_pixels:
        return None
    centre = weighted_median(log_ratio, weight)
    spread = _MAD_TO_SIGMA * weighted_median(np.abs(log_ratio - centre), weight)
    patches = int(len(np.unique(np.concatenate(patch_ids))))
    uncertainty = _MEDIAN_SE * spread / np.sqrt(max(patches, 1))
    return DepthScaleFit(float(np.exp(centre)), float(uncertainty), int(len(log_ratio)), patches)

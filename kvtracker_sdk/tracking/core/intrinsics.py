"""The intrinsics each ``FrameResult`` reports: given, predicted (DA3) or estimated (Pi3).

Order of precedence for a frame:

1. **Given** — the camera passed with the frame or for the session (undistorted if it had a lens
   model): reported as is.
2. **Predicted** — Depth Anything 3's camera decoder gives K of the model-resolution image
   (``TrackResult.intrinsics``); it is carried to the input image's pixels exactly through the
   inverse of the frame's ``PixelTransform`` (``K_in = A⁻¹ K_model``).
3. **Estimated** — Pi3 predicts no intrinsics. Its local points are camera-frame 3D points per
   pixel, so a pinhole model ``u = fx X/Z + cx``, ``v = fy Y/Z + cy`` is fitted to them by
   **linear least squares**, each axis separately (two unknowns each, closed form), weighted by
   the network's confidence, over the current map's keyframes (one camera for the session; the
   map's local points come from the full-attention mapping pass), then carried to the input
   image like a prediction. The fit's error is its RMS reprojection residual in pixels
   (``IntrinsicsFit.rms_px``, logged at DEBUG): ~1e-4 px on exact pinhole points (float32
   points of the simulated backend or of DA3's unprojected depth); the focal of the simulated
   backend is recovered to < 1e-6 (tested at 1 %). It is recomputed once per map, on every
   4th pixel of at most 4 keyframes, which keeps it cheap beside a tracking step
   (``benchmarks/README.md``).

In object mode with crops, each frame (and keyframe) has its own crop, so a map-wide fit has no
single input-image meaning: estimation is skipped there (given and predicted still work).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.geometry.camera import Camera, IntrinsicsSource
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.tracking.core.model_input import PreparedFrame

__all__ = ["FrameIntrinsics", "IntrinsicsFit", "fit_intrinsics"]

_log = get_logger(__name__)
_MIN_POINTS = 16
# The fit runs on the tracking path once per new map: every 4th row and column of at most 4
# keyframes (about 16k points at 224x294) fits a pinhole camera as well as all of them.
_SAMPLE_STRIDE = 4
_MAX_KEYFRAMES = 4


@dataclass(frozen=True)
class IntrinsicsFit:
    """A least-squares pinhole fit: ``K`` (3x3, pixels of the points' image), the RMS residual
    in pixels, and how many points were used."""

    K: np.ndarray
    rms_px: float
    num_points: int


def _fit_axis(ratio: np.ndarray, pixel: np.ndarray, weight: np.ndarray) -> tuple[float, float, np.ndarray]:
    """Weighted LS of ``pixel = f * ratio + c``: (f, c, residuals)."""
    total = weight.sum()
    mean_r, mean_p = (weight * ratio).sum() / total, (weight * pixel).sum() / total
    dr, dp = ratio - mean_r, pixel - mean_p
    focal = (weight * dr * dp).sum() / (weight * dr * dr).sum()
    centre = mean_p - focal * mean_r
    return float(focal), float(centre), pixel - (focal * ratio + centre)


def fit_intrinsics(
    local_points: np.ndarray, confidence: np.ndarray | None = None, *, pixel_step: int = 1
) -> IntrinsicsFit | None:
    """Fit fx, fy, cx, cy to camera-frame points [N, H, W, 3] (or [H, W, 3]).

    Pixel (row i, column j) of the points' grid is at (u, v) = (j, i) * ``pixel_step`` (pixel
    centres at integers; ``pixel_step`` > 1 when the grid samples every n-th pixel of the image,
    e.g. ``points[:, ::2, ::2]``). ``confidence`` [N, H, W] weights the points (None: equal
    weights); points with Z <= 0, non-finite values or zero weight are left out. None when fewer
    than 16 points remain or the points carry no perspective (all rays parallel).
    """
    points = np.asarray(local_points, dtype=np.float64)
    if points.ndim == 3:
        points = points[None]
    count, height, width = points.shape[:3]
    rows, cols = np.meshgrid(
        np.arange(height, dtype=np.float64) * pixel_step,
        np.arange(width, dtype=np.float64) * pixel_step,
        indexing="ij",
    )
    weight = (
        np.ones(points.shape[:3])
        if confidence is None
        else np.asarray(confidence, dtype=np.float64).reshape(count, height, width)
    )
    z = points[..., 2]
    usable = np.isfinite(points).all(axis=-1) & (z > 0) & np.isfinite(weight) & (weight > 0)
    if usable.sum() < _MIN_POINTS:
        return None
    x_ratio = (points[..., 0] / np.where(usable, z, 1.0))[usable]
    y_ratio = (points[..., 1] / np.where(usable, z, 1.0))[usable]
    w = weight[usable]
    u = np.broadcast_to(cols, points.shape[:3])[usable]
    v = np.broadcast_to(rows, points.shape[:3])[usable]
    if np.ptp(x_ratio) <= 1e-12 or np.ptp(y_ratio) <= 1e-12:
        return None
    fx, cx, res_u = _fit_axis(x_ratio, u, w)
    fy, cy, res_v = _fit_axis(y_ratio, v, w)
    if not (fx > 0 and fy > 0):
        return None
    rms = float(np.sqrt((w * (res_u**2 + res_v**2)).sum() / w.sum()))
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return IntrinsicsFit(K, rms, int(usable.sum()))


class FrameIntrinsics:
    """Decides each frame's reported intrinsics (see the module docstring); keeps the estimate
    of the current map, recomputed only when the map object changes."""

    def __init__(self, *, estimate: bool = True) -> None:
        self.estimate = estimate
        self._map: KeyframeMap | None = None  # held, so that its id is not reused
        self._fit: IntrinsicsFit | None = None

    def resolve(
        self,
        frame: PreparedFrame,
        predicted_K: np.ndarray | None,
        kf_map: KeyframeMap | None,
    ) -> tuple[Camera | None, IntrinsicsSource | None]:
        """(camera of the input image, where it came from) for ``frame``; (None, None) if unknown."""
        if frame.camera is not None:
            return frame.camera, IntrinsicsSource.GIVEN
        model_hw = (int(frame.image.shape[0]), int(frame.image.shape[1]))
        if predicted_K is not None:
            return self._to_input(predicted_K, model_hw, frame), IntrinsicsSource.PREDICTED
        fit = self._map_fit(kf_map) if self.estimate else None
        if fit is None:
            return None, None
        return self._to_input(fit.K, model_hw, frame), IntrinsicsSource.ESTIMATED

    def current_fit(self) -> IntrinsicsFit | None:
        return self._fit

    @staticmethod
    def _to_input(K_model: np.ndarray, model_hw: tuple[int, int], frame: PreparedFrame) -> Camera:
        model_camera = Camera.from_K(np.asarray(K_model, dtype=np.float64), model_hw[1], model_hw[0])
        return model_camera.transformed(frame.transform.inverse(), frame.input_size)

    def _map_fit(self, kf_map: KeyframeMap | None) -> IntrinsicsFit | None:
        if kf_map is None:
            return None
        if kf_map is not self._map:
            keyframes = kf_map.keyframes[:_MAX_KEYFRAMES]
            points = np.stack([kf.local_points for kf in keyframes])
            confidence = np.stack([kf.confidence_map for kf in keyframes])
            step = _SAMPLE_STRIDE
            self._fit = fit_intrinsics(
                points[:, ::step, ::step], confidence[:, ::step, ::step], pixel_step=step
            )
            self._map = kf_map
            if self._fit is not None:
                _log.debug("intrinsics_estimated", fx=self._fit.K[0, 0], fy=self._fit.K[1, 1],
                           cx=self._fit.K[0, 2], cy=self._fit.K[1, 2], rms_px=self._fit.rms_px)
        return self._fit


"""The exact map from an input image's pixels to a preprocessed image's pixels.

Every resize, crop and pad that preprocessing applies is an axis-aligned affine map of pixel
coordinates, ``u' = sx * u + ox`` and ``v' = sy * v + oy``. Keeping it as a value lets camera
intrinsics, boxes and projected points follow the image exactly (``K' = A @ K`` with ``A`` the
3x3 form below), instead of each caller re-deriving the half-pixel terms.

Pixel convention (OpenCV's, and that of every K in the SDK): integer coordinates are pixel
*centres*; pixel (0, 0) covers [-0.5, 0.5]². Under it, ``cv2.resize`` from W to W' samples
source x = (x' + 0.5) * W / W' - 0.5, so the forward map is ``sx = W'/W``, ``ox = (sx - 1)/2``;
a crop starting at column c is ``sx = 1``, ``ox = -c``; padding p columns on the left is
``ox = +p``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kvtracker_sdk.errors import InputError

__all__ = ["PixelTransform"]


@dataclass(frozen=True)
class PixelTransform:
    """``(u, v) -> (sx*u + ox, sy*v + oy)`` in pixel-centre coordinates (see module docstring)."""

    sx: float = 1.0
    sy: float = 1.0
    ox: float = 0.0
    oy: float = 0.0

    def __post_init__(self) -> None:
        values = (self.sx, self.sy, self.ox, self.oy)
        if not all(np.isfinite(v) for v in values):
            raise InputError(f"pixel transform must be finite, got {values}")
        if self.sx <= 0 or self.sy <= 0:
            raise InputError(f"pixel transform scales must be positive, got {self.sx}, {self.sy}")

    @classmethod
    def identity(cls) -> PixelTransform:
        return cls()

    @classmethod
    def resize(cls, src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> PixelTransform:
        """The map of ``cv2.resize`` (any interpolation) from (H, W) to (H', W')."""
        (h, w), (dh, dw) = src_hw, dst_hw
        sx, sy = dw / w, dh / h
        return cls(sx=sx, sy=sy, ox=(sx - 1.0) / 2.0, oy=(sy - 1.0) / 2.0)

    @classmethod
    def crop(cls, x0: float, y0: float) -> PixelTransform:
        """Cropping a window whose top-left source pixel is (x0, y0) (or padding, if negative)."""
        return cls(ox=-float(x0), oy=-float(y0))

    def then(self, other: PixelTransform) -> PixelTransform:
        """This transform followed by ``other`` (``other ∘ self``)."""
        return PixelTransform(
            sx=other.sx * self.sx,
            sy=other.sy * self.sy,
            ox=other.sx * self.ox + other.ox,
            oy=other.sy * self.oy + other.oy,
        )

    def inverse(self) -> PixelTransform:
        return PixelTransform(
            sx=1.0 / self.sx, sy=1.0 / self.sy, ox=-self.ox / self.sx, oy=-self.oy / self.sy
        )

    def matrix(self) -> np.ndarray:
        """3x3 float64 ``A`` with ``[u', v', 1]ᵀ = A [u, v, 1]ᵀ``; intrinsics follow as ``A @ K``."""
        return np.array(
            [[self.sx, 0.0, self.ox], [0.0, self.sy, self.oy], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    def apply(self, points_uv: np.ndarray) -> np.ndarray:
        """Map pixel coordinates [..., 2] (float64 out)."""
        uv = np.asarray(points_uv, dtype=np.float64)
        return uv * np.array([self.sx, self.sy]) + np.array([self.ox, self.oy])

    def apply_to_K(self, K: np.ndarray) -> np.ndarray:
        """Intrinsics of the transformed image: ``A @ K`` (3x3, float64)."""
        return self.matrix() @ np.asarray(K, dtype=np.float64)

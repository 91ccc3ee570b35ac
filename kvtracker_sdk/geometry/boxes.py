"""Image boxes and oriented 3D boxes: the shapes an object's region and extent are reported in.

Image boxes are ``(x0, y0, x1, y1)`` in pixels of an image, the convention of every box the SDK
takes or gives (``push_frame(bbox=...)``, ``preprocess.masks``): pixel (column c, row r) covers
``[c, c + 1) x [r, r + 1)``, so ``x1``/``y1`` are exclusive and a mask's tight box is
``(c_min, r_min, c_max + 1, r_max + 1)``. A *projected* point's pixel coordinate u (pixel centres
at integers, ``geometry/camera.py``) lies at ``u + 0.5`` in box coordinates.

``OrientedBox``: a box with its own axes, placed by a rigid ``T_ref_box`` in some reference frame
(the caller names it), and its half sizes along the box's x, y, z axes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ImageBox", "OrientedBox", "box_iou", "grow_box", "mask_box"]

ImageBox = tuple[float, float, float, float]  # (x0, y0, x1, y1), pixels, x1/y1 exclusive


def box_iou(a: ImageBox, b: ImageBox) -> float:
    """Intersection over union of two boxes (0 when either is empty)."""
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    area_a = max(0.0, a[2] - a[0]) * max(0.0, a[3] - a[1])
    area_b = max(0.0, b[2] - b[0]) * max(0.0, b[3] - b[1])
    union = area_a + area_b - inter
    return float(inter / union) if union > 0 else 0.0


def grow_box(box: ImageBox, margin: float, size: tuple[int, int]) -> ImageBox:
    """``box`` dilated by ``margin`` pixels on every side, clipped to an image of ``size`` (H, W)."""
    height, width = size
    x0, y0, x1, y1 = box
    return (
        max(0.0, x0 - margin), max(0.0, y0 - margin),
        min(float(width), x1 + margin), min(float(height), y1 + margin),
    )  # fmt: skip


def mask_box(mask: np.ndarray) -> ImageBox | None:
    """The tight box of a bool [H, W] mask's pixels (None when it selects none)."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return None
    return float(cols[0]), float(rows[0]), float(cols[-1] + 1), float(rows[-1] + 1)


@dataclass(frozen=True)
class OrientedBox:
    """A 3D box: ``T_ref_box`` (4x4 rigid, the box's centre and axes in the reference frame) and
    ``half_extents`` [3] (half its size along its own x, y, z; units of the reference frame)."""

    T_ref_box: np.ndarray
    half_extents: np.ndarray

    def __post_init__(self) -> None:
        for name in ("T_ref_box", "half_extents"):
            value = np.array(getattr(self, name), dtype=np.float64, copy=True)
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    @property
    def centre(self) -> np.ndarray:
        return self.T_ref_box[:3, 3]

    @property
    def size(self) -> np.ndarray:
        """Full edge lengths [3] along the box's axes."""
        return 2.0 * self.half_extents

    def corners(self) -> np.ndarray:
        """[8, 3] corners in the reference frame."""
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        local = signs * self.half_extents
        return local @ self.T_ref_box[:3, :3].T + self.T_ref_box[:3, 3]

    def transformed(self, T_new_ref: np.ndarray) -> OrientedBox:
        """The same box with its pose expressed in another frame (``T_new_ref`` rigid)."""
        return OrientedBox(np.asarray(T_new_ref, dtype=np.float64) @ self.T_ref_box,
                           self.half_extents)

    @classmethod
    def fit(cls, points: np.ndarray, *, trim: float = 0.01) -> OrientedBox:
        """The box along the principal axes of ``points`` [N, 3] (N >= 1) holding all but a
        fraction ``trim`` of them on each side of each axis (robust to a few stray points).

        Principal axes (eigenvectors of the covariance, largest first, made right-handed) rather
        than a minimum-volume box: stable from frame to frame for a noisy, growing point set.
        """
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        mean = pts.mean(axis=0)
        centred = pts - mean
        if len(pts) >= 3:
            _, vectors = np.linalg.eigh(centred.T @ centred)
            axes = vectors[:, ::-1]  # largest spread first
        else:
            axes = np.eye(3)
        if np.linalg.det(axes) < 0:
            axes[:, 2] = -axes[:, 2]
        local = centred @ axes
        low, high = np.quantile(local, [trim, 1.0 - trim], axis=0)
        pose = np.eye(4)
        pose[:3, :3] = axes
        pose[:3, 3] = mean + axes @ ((low + high) / 2.0)
        return cls(pose, (high - low) / 2.0)

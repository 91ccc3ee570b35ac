"""Depth frames from an RGB-D sensor: validation, units, and resampling to the model image.

Accepted (``push_frame(depth=..., depth_scale=...)``): numpy [H, W] (or [H, W, 1]) registered to
the colour image pushed with it (same H, W: pixel (u, v) of both sees the same ray), either

* float (metres), ``depth_scale`` omitted (or a factor to metres), or
* integer raw units with ``depth_scale`` = metres per unit (RealSense 0.001, TUM's 16-bit PNGs
  1/5000, Kinect for Azure 0.001).

Invalid pixels are 0 (NaN and inf are taken as invalid too: several SDKs mark holes so). A
negative depth is a typed ``DepthError``: it is a wrong sign or a wrong dtype, not a hole.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from kvtracker_sdk.errors import DepthError
from kvtracker_sdk.geometry.pixel_transform import PixelTransform

__all__ = ["check_depth", "depth_to_model"]


def _checked_scale(depth_scale: Any, *, required: bool) -> float:
    if depth_scale is None:
        if required:
            raise DepthError(
                "an integer depth image needs depth_scale (metres per unit, e.g. 0.001 for "
                "millimetres, 1/5000 for TUM PNGs); float depth is taken as metres"
            )
        return 1.0
    try:
        scale = float(depth_scale)
    except (TypeError, ValueError, OverflowError) as exc:
        raise DepthError(f"depth_scale must be a number, got {str(depth_scale)[:40]}") from exc
    if not (math.isfinite(scale) and scale > 0):
        raise DepthError(f"depth_scale must be finite and > 0 (metres per unit), got {scale}")
    return scale


def check_depth(depth: Any, depth_scale: Any, size: tuple[int, int]) -> np.ndarray:
    """float32 [H, W] metres (0 = invalid) of a depth image for a colour image of ``size``
    (H, W); raises ``DepthError`` and changes nothing otherwise."""
    if not isinstance(depth, np.ndarray):
        raise DepthError(f"depth must be a numpy array, got {type(depth).__name__}")
    if depth.ndim == 3 and depth.shape[2] == 1:
        depth = depth[..., 0]
    if depth.shape != tuple(size):
        raise DepthError(
            f"depth shape {depth.shape} does not match the colour image's {tuple(size)}: "
            "register the depth to the colour camera first"
        )
    if np.issubdtype(depth.dtype, np.integer) or depth.dtype == np.bool_:
        if depth.dtype == np.bool_:
            raise DepthError("depth must be numbers (raw units or metres), got a bool array")
        scale = _checked_scale(depth_scale, required=True)
        if depth.dtype.kind == "i" and depth.min() < 0:
            raise DepthError("depth has negative values (invalid pixels must be 0)")
        return (depth.astype(np.float64) * scale).astype(np.float32)
    if not np.issubdtype(depth.dtype, np.floating):
        raise DepthError(f"depth dtype must be integer (raw) or float (metres), got {depth.dtype}")
    scale = _checked_scale(depth_scale, required=False)
    metres = np.asarray(depth, dtype=np.float64) * scale
    valid = np.isfinite(metres)
    if (metres[valid] < 0).any():
        raise DepthError("depth has negative values (invalid pixels must be 0)")
    out = np.where(valid, metres, 0.0).astype(np.float32)
    if not np.isfinite(out).all():  # a finite float64 beyond float32's range
        raise DepthError("depth values overflow float32 metres: check depth_scale")
    return out


def depth_to_model(
    depth: np.ndarray, transform: PixelTransform, out_size: tuple[int, int]
) -> np.ndarray:
    """float32 [h, w] depth of the model image (``out_size``) sampled from ``depth`` [H, W]
    (metres) through the prepared frame's pixel ``transform`` (input pixel -> model pixel).

    Nearest neighbour, on purpose: interpolating would average a foreground and a background
    depth at an edge into a depth where nothing is, and would blend valid pixels with holes (0).
    Model pixels whose source lies outside the input image (padding) are 0.
    """
    height, width = out_size
    back = transform.inverse()
    cols = np.rint(back.sx * np.arange(width) + back.ox).astype(np.int64)
    rows = np.rint(back.sy * np.arange(height) + back.oy).astype(np.int64)
    col_ok = (cols >= 0) & (cols < depth.shape[1])
    row_ok = (rows >= 0) & (rows < depth.shape[0])
    sampled = depth[np.clip(rows, 0, depth.shape[0] - 1)[:, None],
                    np.clip(cols, 0, depth.shape[1] - 1)[None, :]]
    sampled = np.where(row_ok[:, None] & col_ok[None, :], sampled, 0.0)
    return np.ascontiguousarray(sampled, dtype=np.float32)

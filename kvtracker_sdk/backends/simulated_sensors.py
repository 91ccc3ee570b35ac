"""Simulated RGB-D and IMU readings beside ``SimulatedCamera`` frames, for metric-scale and gravity
tests without hardware.

* ``sensor_depth``: the scene's true depth (metres, ray cast) as a depth sensor delivers it —
  multiplicative noise (``noise`` of the depth, 1-sigma), a fraction of pixels missing at random,
  and pixels at depth edges invalid (a sensor's flying pixels there are masked out by its
  driver); invalid = 0.
* ``gravity_reading``: gravity in the camera frame (OpenCV axes, pointing down, m/s²) with white
  noise per axis, as an accelerometer at rest gives it (negated).

The simulated *network* (``SimulatedBackend``) answers each mapping pass in a hidden frame of
random scale, so its map is in arbitrary units: the first pass's scale, ``exp(U(-1.6, 1.6))``
world units per metre (0.20 for ``seed=0``). Metric scale therefore has to come from these
readings, as it would from a real sensor.
"""

from __future__ import annotations

import numpy as np

from kvtracker_sdk.backends.simulated_scene import SimulatedScene, camera_matrix, pixel_rays

__all__ = ["STANDARD_GRAVITY", "gravity_reading", "sensor_depth"]

STANDARD_GRAVITY = 9.80665  # m/s²


def sensor_depth(
    scene: SimulatedScene,
    T_world_cam: np.ndarray,
    size: tuple[int, int],
    *,
    rng: np.random.Generator,
    noise: float = 0.01,
    missing: float = 0.05,
    edge_jump: float = 0.05,
    K: np.ndarray | None = None,
) -> np.ndarray:
    """float32 [H, W] depth in metres of a camera at ``T_world_cam`` (0 = invalid).

    ``noise``: relative 1-sigma; ``missing``: fraction of pixels dropped at random;
    ``edge_jump``: a pixel whose depth differs from a 4-neighbour's by more than this fraction
    is invalid (both sides of a depth edge). ``K``: intrinsics (default ``camera_matrix(size)``,
    the colour frames'), so the depth is registered to the colour image.
    """
    depth, _ = scene.depth(T_world_cam, pixel_rays(size, camera_matrix(size) if K is None else K))
    edges = np.zeros(depth.shape, dtype=bool)
    for axis in (0, 1):
        jump = np.abs(np.diff(depth, axis=axis)) > edge_jump * np.minimum(
            np.delete(depth, -1, axis=axis), np.delete(depth, 0, axis=axis))
        pad_after = [(0, 1) if a == axis else (0, 0) for a in (0, 1)]
        pad_before = [(1, 0) if a == axis else (0, 0) for a in (0, 1)]
        edges |= np.pad(jump, pad_after) | np.pad(jump, pad_before)
    noisy = depth * (1.0 + noise * rng.standard_normal(depth.shape))
    invalid = edges | (rng.random(depth.shape) < missing) | ~np.isfinite(noisy) | (noisy <= 0)
    return np.where(invalid, 0.0, noisy).astype(np.float32)


def gravity_reading(
    T_world_cam: np.ndarray,
    *,
    rng: np.random.Generator,
    noise: float = 0.05,
    up: tuple[float, float, float] = (0.0, 0.0, 1.0),
) -> np.ndarray:
    """float64 [3] gravity (pointing down, m/s²) in the camera frame of ``T_world_cam``, with
    ``noise`` m/s² white noise per axis; ``up``: the world's true up (the simulated scenes'
    world z)."""
    down_world = -STANDARD_GRAVITY * np.asarray(up, dtype=np.float64)
    return T_world_cam[:3, :3].T @ down_world + noise * rng.standard_normal(3)

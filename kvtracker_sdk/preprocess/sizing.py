"""Model input sizes: which (H, W) each family's official pipeline resizes a frame to.

Each function returns a *plan*: the resize steps, in order, from the source size to the model
input size. Most plans have one step; Depth Anything 3's has two (longest side first, then each
side to a multiple of the patch), and the second step's filter depends on the first step's size,
so the steps are kept rather than only the final size.

* ``pi3_kvtracker_plan``: as the KV-Tracker code prepares Pi3 frames at side ``d`` (the same
  arithmetic as Pi3's own ``load_images_as_tensor`` with ``PIXEL_LIMIT = d²``): scale to the pixel
  budget, **round** W/14 and H/14, then take one patch off the side whose ratio is too large until
  the budget holds. One bilinear resize.
* ``da3_upper_bound_plan``: Depth Anything 3's ``InputProcessor`` with ``upper_bound_resize``: the
  longest side becomes ``d`` (each side ``round(side * d / longest)``; area when shrinking, cubic
  when enlarging; skipped when the longest side already is ``d``), then each side goes to its
  nearest multiple of 14 (ties upwards) by a second resize (cubic if either side grows, else
  area; skipped when already divisible).
* ``legacy_area_floor_plan``: what this SDK did before (each side floored to a multiple of the
  patch within d² pixels; area down, cubic up). Kept so that maps saved with it keep tracking.

Rounding is Python's ``round`` (half to even), as in both official pipelines.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2

__all__ = [
    "ResizeStep",
    "da3_upper_bound_plan",
    "legacy_area_floor_plan",
    "pi3_kvtracker_plan",
    "plan_output_size",
]

Size = tuple[int, int]  # (H, W)


class ResizeStep(NamedTuple):
    """One ``cv2.resize`` to ``size`` (H, W) with OpenCV ``interpolation`` (``cv2.INTER_*``)."""

    size: Size
    interpolation: int


def _check_size(height: int, width: int, side: int, patch_size: int) -> None:
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive, got {height}x{width}")
    if side <= 0 or patch_size <= 0:
        raise ValueError(f"side and patch size must be positive, got {side}, {patch_size}")


def plan_output_size(source: Size, plan: tuple[ResizeStep, ...]) -> Size:
    """(H, W) after ``plan`` (the source size for an empty plan)."""
    return plan[-1].size if plan else source


def pi3_kvtracker_plan(source: Size, side: int, patch_size: int = 14) -> tuple[ResizeStep, ...]:
    """KV-Tracker's Pi3 sizing at ``side`` d: at most d² pixels, multiples of ``patch_size``."""
    height, width = source
    _check_size(height, width, side, patch_size)
    budget = side * side
    scale = math.sqrt(budget / (width * height))
    target_w, target_h = width * scale, height * scale
    cols, rows = round(target_w / patch_size), round(target_h / patch_size)
    cols, rows = max(cols, 1), max(rows, 1)
    # shrink the side whose patch ratio exceeds the image's until the budget holds
    while cols * rows * patch_size * patch_size > budget and cols * rows > 1:
        too_wide = cols / rows > target_w / target_h
        if (too_wide and cols > 1) or rows == 1:
            cols -= 1
        else:
            rows -= 1
    size = (rows * patch_size, cols * patch_size)
    return () if size == source else (ResizeStep(size, cv2.INTER_LINEAR),)


def _nearest_multiple(value: int, patch_size: int) -> int:
    """The multiple of ``patch_size`` nearest ``value``; a tie goes up (DA3's rule), never 0."""
    down = value // patch_size * patch_size
    up = down + patch_size
    return up if up - value <= value - down or down == 0 else down


def da3_upper_bound_plan(source: Size, side: int, patch_size: int = 14) -> tuple[ResizeStep, ...]:
    """Depth Anything 3's ``upper_bound_resize`` at ``process_res`` = ``side``."""
    height, width = source
    _check_size(height, width, side, patch_size)
    steps: list[ResizeStep] = []
    longest = max(height, width)
    if longest != side:
        scale = side / longest
        height, width = max(1, round(height * scale)), max(1, round(width * scale))
        shrink = cv2.INTER_AREA if scale <= 1.0 else cv2.INTER_CUBIC
        steps.append(ResizeStep((height, width), shrink))
    rounded = (_nearest_multiple(height, patch_size), _nearest_multiple(width, patch_size))
    if rounded != (height, width):
        grows = rounded[0] > height or rounded[1] > width
        steps.append(ResizeStep(rounded, cv2.INTER_CUBIC if grows else cv2.INTER_AREA))
    return tuple(steps)


def legacy_area_floor_plan(
    source: Size, side: int, patch_size: int = 14
) -> tuple[ResizeStep, ...]:
    """The SDK's earlier sizing, kept for maps saved with it: floor each side to the patch
    within d² pixels."""
    height, width = source
    _check_size(height, width, side, patch_size)
    scale = math.sqrt(side * side / (height * width))
    size = (
        max(patch_size, int(height * scale) // patch_size * patch_size),
        max(patch_size, int(width * scale) // patch_size * patch_size),
    )
    if size == source:
        return ()
    shrinking = size[0] * size[1] < height * width
    return (ResizeStep(size, cv2.INTER_AREA if shrinking else cv2.INTER_CUBIC),)

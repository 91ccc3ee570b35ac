"""Checks of numeric command-line options, applied by Typer while parsing (before anything runs).

Integer ranges use Typer's own ``min``/``max``; floats also need :func:`finite`, because
Click's range check compares with ``<``/``>``, which ``nan`` passes.
"""

from __future__ import annotations

import math

import typer

__all__ = ["MAX_PORT", "MAX_SIMULATED_FRAMES", "finite"]

MAX_PORT = 65535  # TCP ports are 16-bit; 0 asks the system for any free one
# backends.simulated_scene.MAX_FRAMES (the frames a simulated camera can number; a test pins the
# two equal): not imported, so that parsing options does not load torch
MAX_SIMULATED_FRAMES = 224 * 224


def finite(value: float | None) -> float | None:
    """A Typer ``callback``: ``value`` unless it is NaN or infinite (a usage error, exit 2)."""
    if value is not None and not math.isfinite(value):
        raise typer.BadParameter(f"must be a finite number, got {value}")
    return value

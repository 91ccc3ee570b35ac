"""Float frames are resized before they are converted: memory stays at the frame's own size."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.tracking.core.model_input import FramePreparer


def _preparer(family: str = "pi3") -> FramePreparer:
    return FramePreparer(TrackerConfig(resolution=224), patch_size=14, family=family)


def test_a_large_float_frame_costs_no_full_size_temporary() -> None:
    """2000x2000 float64 (96 MB): converting first made float32 copies of the whole frame
    (astype, clip, scale, round: 48 MB each, plus a 12 MB isfinite mask), peaking ~100+ MB
    above the frame. Resizing first keeps the peak to the model-size arrays (~1 MB)."""
    frame = np.full((2000, 2000, 3), 0.5, dtype=np.float64)
    frame[::7, ::5, 1] = 0.25  # not constant, so nothing can be short-cut
    preparer = _preparer()
    tracemalloc.start()
    try:
        prepared = preparer.prepare(frame)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert prepared.image.shape == (224, 224, 3) and prepared.image.dtype == np.uint8
    assert peak < 8 * 2**20, f"peak {peak / 2**20:.1f} MiB above the frame"


@pytest.mark.parametrize("family", ["pi3", "da3"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.float16])
def test_float_frames_match_their_uint8_twin_within_a_level(family: str, dtype: type) -> None:
    rng = np.random.default_rng(11)
    uint8 = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
    as_float = (uint8 / 255.0).astype(dtype)
    a = _preparer(family).prepare(uint8).image
    b = _preparer(family).prepare(as_float).image
    assert a.shape == b.shape
    # resize-then-round vs round-then-resize: one rounding apart (float16 keeps 11 bits: k/255
    # is off by < 1/2048, so one more level at most)
    limit = 2 if dtype is np.float16 else 1
    assert int(np.abs(a.astype(np.int16) - b.astype(np.int16)).max()) <= limit

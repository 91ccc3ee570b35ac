"""The accuracy proxy of compact caches on the golden Pi3 and DA3 over real TUM frames.

Four of the 20 TUM frames (two keyframes, two tracked), golden reduced models (random weights):
int8 must move tracked poses and points no further from the fp32 cache than the bf16 backend
does, with a cache at least 1.9x smaller than bf16's. Measured here (224 px, frames 0/6/12/18):
int8 deviates 10-30x less than bf16 (benchmarks/results/compact_maps*.json has all 20 frames).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from kvtracker_sdk.eval.cache_deviation import CacheVariant, cache_deviation, tum_frames
from kvtracker_sdk.io.sources.sources import TumSource
from tests.helpers import shared_path


@pytest.mark.parametrize("family", ["pi3", "da3"])
def test_int8_deviates_no_more_than_bf16_and_is_1_9x_smaller(family: str) -> None:
    frames = list(TumSource(shared_path("data", "tum_fr2_desk")))[::6]
    images = tum_frames(frames, family, resolution=224)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny model: one thread is as fast and does not fight other jobs
    try:
        rows = cache_deviation(
            shared_path("golden", family, "weights.safetensors"),
            images,
            keyframes=[0, 2],
            variants=[CacheVariant("bf16", dtype="bfloat16"), CacheVariant("int8", storage="int8")],
        )
    finally:
        torch.set_num_threads(threads)
    reference, bf16, int8 = rows
    assert reference.pose_max == 0.0 and reference.rotation_deg_max == 0.0
    assert 0.0 < int8.pose_max <= bf16.pose_max
    assert 0.0 < int8.points_median <= bf16.points_median
    assert int8.rotation_deg_max <= bf16.rotation_deg_max
    assert bf16.cache_bytes / int8.cache_bytes >= 1.9
    assert np.isfinite([int8.pose_median, int8.points_median]).all()

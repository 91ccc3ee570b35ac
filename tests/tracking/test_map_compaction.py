"""Compact maps in the tracker (``TrackerConfig.compaction``) on a tiny random Pi3: every
rebuild's cache is pruned, a pruned map saved and loaded tracks identically, and incremental
keyframes keep the tracking pass's K/V with a full rebuild every ``rebuild_every`` insertions."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from kvtracker_sdk.tracking.facade.tracker import Tracker

torch = pytest.importorskip("torch")

SIZE = (196, 252)  # model input 196x252 at 224: 14x18 patches + 5 registers


def _tracker(**compaction: Any) -> Tracker:
    from kvtracker_sdk.backends.torch_backend import TorchBackend
    from tests.models.pi3.factories import random_pi3, tiny_config

    config = {
        "resolution": 224,
        "keyframing": {"interval_frames": 2},
        "rejection": {"enabled": False},  # random weights: keep every candidate
        "compaction": compaction,
    }
    return Tracker(config, TorchBackend(random_pi3(tiny_config(), seed=5)))


def _image(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (*SIZE, 3), dtype=np.uint8)


def test_rebuilt_maps_are_pruned_and_a_saved_one_tracks_identically(tmp_path: Path) -> None:
    with _tracker(keep_ratio=0.5) as tracker:
        for i in range(5):  # keyframes at frames 0, 2, 4
            tracker.push_frame(_image(i))
        kf_map = tracker.keyframe_map
        assert kf_map is not None and kf_map.keyframe_ids == (0, 1, 2)
        cache = kf_map.cache
        budget = math.ceil(0.5 * 3 * cache.tokens_per_frame)
        assert cache.pruned and {cache.layer_length(i) for i in range(cache.layout.num_layers)} == {budget}
        assert tracker.map_status.cache_bytes == cache.nbytes  # the pruned size
        tracker.save_map(tmp_path / "pruned.kvmap")
        pose = tracker.push_frame(_image(7)).pose
        backend = tracker.backend
        with Tracker.from_map(tmp_path / "pruned.kvmap", backend) as loaded:
            assert loaded.keyframe_map is not None and loaded.keyframe_map.cache.equals(cache)
            again = loaded.push_frame(_image(7)).pose
    assert pose is not None and again is not None
    np.testing.assert_array_equal(again.T_world_cam, pose.T_world_cam)


def test_incremental_keyframes_keep_the_tracking_pass_kv_and_rebuild_every_k() -> None:
    with _tracker(incremental_keyframes=True, rebuild_every=2, rebuild_below=0.01) as tracker:
        tracker.push_frame(_image(0))  # bootstrap: a full pass
        insertions, maps = [], []
        for i in range(1, 7):
            before = tracker.keyframe_map
            result = tracker.push_frame(_image(i))
            kf_map = tracker.keyframe_map
            assert kf_map is not None and before is not None
            if result.is_keyframe:
                insertions.append(kf_map.insertions)
                maps.append((before, kf_map, i))
        backend = tracker.backend
        assert insertions == [1, 2, 0]  # two insertions, then a full rebuild
        before, after, frame = maps[0]
        T = before.cache.tokens_per_frame
        # keyframe 0 kept its K/V and pose; the new one has the K/V of a pass against the map
        probe = before.cache.clone()
        image = after.keyframes[-1].image
        backend.track(image, probe)
        for layer in range(probe.layout.num_layers):
            assert torch.equal(after.cache.keys(layer)[:, :, :T], before.cache.keys(layer))
            scratch = probe.buffers(layer)[0][:, :, T : 2 * T]
            assert torch.allclose(after.cache.keys(layer)[:, :, T:], scratch, atol=1e-6)
        np.testing.assert_array_equal(after.keyframes[0].T_world_cam, before.keyframes[0].T_world_cam)

"""The tracker with ``cache_dtype`` int8: quantised maps in memory and in files, and the backends
that cannot read them (golden Pi3 over 5 real TUM frames, 224 px; the simulated backend)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import pytest
import torch

from kvtracker_sdk.backends.frame_checks import check_cache
from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import orbit
from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.errors import BackendMismatchError, ConfigError
from kvtracker_sdk.tracking.facade.tracker import Tracker
from kvtracker_sdk.tracking.persistence import tracker_maps as persistence
from tests.helpers import shared_path


def test_a_backend_that_cannot_read_quantised_caches_refuses_the_config() -> None:
    with pytest.raises(ConfigError, match="needs the PyTorch backend"):
        Tracker({"cache_dtype": "int8"}, SimulatedBackend(orbit(num_frames=10)))


def test_int8_maps_in_the_tracker_and_in_files(tmp_path: Path) -> None:
    files = sorted(shared_path("data", "tum_fr2_desk", "rgb").glob("*.png"))[:5]
    frames = [cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB) for f in files]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny model: one thread is as fast and does not fight other jobs
    try:
        backend = TorchBackend.from_pretrained(shared_path("golden", "pi3", "weights.safetensors"))
        config = {"resolution": 224, "cache_dtype": "int8", "keyframing": {"interval_frames": 2}}
        with Tracker(config, backend) as tracker:
            results = [tracker.push_frame(image) for image in frames]
            cache = tracker.keyframe_map.cache
            assert tracker.map_status.cache_bytes == cache.nbytes
            tracker.save_map(tmp_path / "int8.kvmap")
        assert cache.storage == "int8" and cache.dtype == torch.float32
        assert cache.num_keyframes >= 2 and all(r.pose is not None for r in results)
        with Tracker.from_map(tmp_path / "int8.kvmap", backend) as again:
            assert again.keyframe_map.cache.equals(cache) and again.config.cache_dtype == "int8"
            assert again.push_frame(frames[-1]).pose is not None
    finally:
        torch.set_num_threads(threads)
    onnx_like = replace(backend.info, backend="onnx")
    with pytest.raises(BackendMismatchError, match="cannot track against a quantised"):
        check_cache(cache, onnx_like, 196, 252)
    loaded = persistence.load_tracker_map(tmp_path / "int8.kvmap", onnx_like)
    dense = loaded.keyframe_map.cache  # dequantised once, for a graph that takes the whole cache
    assert not dense.quantized and dense.dtype == torch.float32
    assert torch.equal(dense.keys(0), cache.keys(0)) and loaded.config.cache_dtype == "backend"

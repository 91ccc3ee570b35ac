"""The exported graphs under ONNX Runtime reproduce the golden Pi3 vectors (``../shared/golden/pi3``).

``OnnxRunner`` is driven with the golden float images directly (the backend's uint8 path is
tested in ``test_onnx.py``). Tolerances: the golden README's fp32 ones — camera_poses atol 1e-5,
conf logits atol 1e-4 (confidence = sigmoid(logit): atol 2.5e-5), points/local_points atol 1e-4 + rtol 1e-4, K/V atol 1e-5.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file
from scipy.special import expit

from kvtracker_sdk.backends.onnx_manifest import read_manifest
from kvtracker_sdk.backends.onnx_runtime import OnnxRunner
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.models.family import FrameOutputs as HeadOutputs
from kvtracker_sdk.models.pi3 import load_pi3
from kvtracker_sdk.models.pi3.conventions import camera_poses
from kvtracker_sdk.models.pi3.heads import rotation_from_matrix9
from kvtracker_sdk.types import HeadSet
from tests.helpers import shared_path

CASES = {"case1": (3, ["query"]), "case2": (5, ["query5", "query_flip"])}  # keyframes, queries


@pytest.fixture(scope="module")
def runner(golden_onnx_dir: Path) -> OnnxRunner:
    return OnnxRunner(golden_onnx_dir, read_manifest(golden_onnx_dir), threads=1)


def golden(case: str, name: str) -> dict[str, np.ndarray]:
    path = shared_path("golden", "pi3", case, f"{name}.safetensors")
    return {key: value.numpy() for key, value in load_file(path).items()}


def assert_matches(outputs: HeadOutputs, expected: dict[str, np.ndarray], prefix: str) -> None:
    """Compare [F, ...] outputs with golden [1, F, ...] tensors named ``prefix + output``."""
    np.testing.assert_allclose(
        outputs.poses, expected[prefix + "camera_poses"][0], atol=1e-5, rtol=0
    )
    assert outputs.confidence is not None and outputs.local_points is not None
    np.testing.assert_allclose(
        outputs.confidence, expit(expected[prefix + "conf"][0, ..., 0]), atol=2.5e-5, rtol=0
    )
    np.testing.assert_allclose(
        outputs.local_points, expected[prefix + "local_points"][0], atol=1e-4, rtol=1e-4
    )
    rotation, translation = (
        outputs.poses[:, None, None, :3, :3],
        outputs.poses[:, None, None, :3, 3],
    )
    points = (rotation @ outputs.local_points[..., None])[..., 0] + translation  # world frame
    np.testing.assert_allclose(points, expected[prefix + "points"][0], atol=1e-4, rtol=1e-4)


def query_image(imgs: np.ndarray, keyframes: int, name: str) -> np.ndarray:
    """[1, 3, H, W]: the frame after the keyframes, flipped on W for ``query_flip``."""
    frame = imgs[0, keyframes : keyframes + 1]
    return np.ascontiguousarray(frame[..., ::-1]) if name == "query_flip" else frame


def cache_from_map(
    runner: OnnxRunner, keys: list[np.ndarray], values: list[np.ndarray], tokens_per_frame: int
) -> KVCache:
    return KVCache.from_layers(
        [torch.from_numpy(k) for k in keys],
        [torch.from_numpy(v) for v in values],
        layout=runner.manifest.cache_layout,
        tokens_per_frame=tokens_per_frame,
        keyframe_ids=range(keys[0].shape[2] // tokens_per_frame),
    )


def buffers(cache: KVCache) -> list[tuple[np.ndarray, np.ndarray]]:
    return [(k.numpy(), v.numpy()) for k, v in map(cache.buffers, range(cache.layout.num_layers))]


@pytest.mark.parametrize("case", sorted(CASES))
def test_mapping_all_frames_is_the_official_forward(runner: OnnxRunner, case: str) -> None:
    outputs, _, _ = runner.map(golden(case, "inputs")["imgs"][0])
    assert_matches(outputs, golden(case, "outputs"), prefix="")


@pytest.mark.parametrize("case", sorted(CASES))
def test_mapping_and_queries_through_the_cache_input(runner: OnnxRunner, case: str) -> None:
    keyframes, queries = CASES[case]
    imgs = golden(case, "inputs")["imgs"]
    outputs, keys, values = runner.map(imgs[0, :keyframes])
    expected = golden(case, "outputs_query")
    assert_matches(outputs, expected, prefix="keyframes.")
    kv = golden(case, "kv_cache")
    for layer, block in enumerate(runner.manifest.cache_layout.block_indices):
        np.testing.assert_allclose(keys[layer], kv[f"layer{block}.k"], atol=1e-5, rtol=0)
        np.testing.assert_allclose(values[layer], kv[f"layer{block}.v"], atol=1e-5, rtol=0)

    tokens = kv["keyframe_pos"].shape[1] // keyframes
    cache = cache_from_map(runner, keys, values, tokens)
    before = cache.clone()
    for name in queries:  # one after the other against the same cache (two queries in case2)
        tracked = runner.track(
            query_image(imgs, keyframes, name), buffers(cache), cache.length, HeadSet.ALL
        )
        assert_matches(tracked, expected, prefix=f"{name}.")
    assert cache.equals(before)


def test_one_tracking_graph_serves_caches_of_any_length(runner: OnnxRunner) -> None:
    """Caches of 1 to 5 keyframes, as KVCache buffers with scratch or compact, through one graph."""
    imgs = golden("case2", "inputs")["imgs"]
    model = load_pi3(shared_path("golden", "pi3", "weights.safetensors")).model
    query = query_image(imgs, 5, "query5")
    poses = []
    for keyframes in (1, 2, 3, 5):
        _, keys, values = runner.map(imgs[0, :keyframes])
        cache = cache_from_map(runner, keys, values, tokens_per_frame=75)
        assert cache.capacity > cache.length  # the graph gets scratch tokens after the cache
        with torch.no_grad():
            expected = model.forward_track(torch.from_numpy(query), cache, heads=HeadSet.CAMERA)
        tracked = runner.track(query, buffers(cache), cache.length, HeadSet.CAMERA)
        np.testing.assert_allclose(tracked.poses, expected.camera_poses[:, 0], atol=1e-5, rtol=0)
        compact = runner.track(
            query, list(zip(keys, values, strict=True)), cache.length, HeadSet.CAMERA
        )
        np.testing.assert_allclose(compact.poses, tracked.poses, atol=1e-6, rtol=0)
        poses.append(tracked.poses)
    assert np.abs(poses[0] - poses[-1]).max() > 1e-3  # the cache's length changes the result


def test_scratch_tokens_after_the_cache_are_ignored(runner: OnnxRunner) -> None:
    imgs = golden("case1", "inputs")["imgs"]
    _, keys, values = runner.map(imgs[0, :3])
    cache = cache_from_map(runner, keys, values, tokens_per_frame=93)
    clean = runner.track(imgs[0, 3:], buffers(cache), cache.length, HeadSet.ALL)
    for key, value in buffers(cache):
        key[:, :, cache.length :] = np.nan
        value[:, :, cache.length :] = np.inf
    dirty = runner.track(imgs[0, 3:], buffers(cache), cache.length, HeadSet.ALL)
    assert dirty.confidence is not None and clean.confidence is not None
    np.testing.assert_array_equal(dirty.poses, clean.poses)
    np.testing.assert_array_equal(dirty.confidence, clean.confidence)


@pytest.mark.parametrize("heads", list(HeadSet))
def test_head_sets_run_only_their_graphs(runner: OnnxRunner, heads: HeadSet) -> None:
    imgs = golden("case1", "inputs")["imgs"]
    _, keys, values = runner.map(imgs[0, :3])
    tracked = runner.track(
        imgs[0, 3:], list(zip(keys, values, strict=True)), keys[0].shape[2], heads
    )
    assert tracked.poses.shape == (1, 4, 4)
    assert (tracked.confidence is None) == (heads is HeadSet.CAMERA)
    assert (tracked.local_points is None) == (heads is not HeadSet.ALL)


def test_camera_poses_match_the_torch_head() -> None:
    """The numpy row-normalise + SVD is the PyTorch head's function, reflections included.

    Against the torch head run in float64 it agrees to 1e-12. The PyTorch backend runs the head
    in float32, whose SVD rounding reaches ~1e-6 (median 3e-7 on random matrices, ~2e-5 on
    nearly degenerate ones): that comparison gets 1e-5.
    """
    raw = torch.randn(64, 9, generator=torch.Generator().manual_seed(3)) * 2.0
    raw[::2, :3] *= -1.0  # flip a row of every other matrix: det < 0 before the projection
    translation = torch.randn(64, 3, generator=torch.Generator().manual_seed(4))
    poses = camera_poses(raw.numpy(), translation.numpy())
    np.testing.assert_allclose(
        poses[:, :3, :3], rotation_from_matrix9(raw.double()).numpy(), atol=1e-12, rtol=0
    )
    np.testing.assert_allclose(
        poses[:, :3, :3], rotation_from_matrix9(raw).double().numpy(), atol=1e-5, rtol=0
    )
    np.testing.assert_array_equal(poses[:, :3, 3], translation.double().numpy())
    np.testing.assert_allclose(np.linalg.det(poses[:, :3, :3]), 1.0, atol=1e-12)
    assert poses.dtype == np.float64 and (poses[:, 3] == [0, 0, 0, 1]).all()

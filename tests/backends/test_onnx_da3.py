"""Depth Anything 3 on ONNX Runtime: the golden vectors (``../shared/golden/da3``) through the
exported graphs, and a Pi3 cache refused (``OnnxBackend`` against ``TorchBackend``, for both
families: ``test_onnx_backend_families.py``).

The runner is driven with the golden float images; its outputs are in the SDK's conventions, so
the golden DA3 outputs are converted the way ``TorchBackend`` converts them: ``T_world_cam`` is
the inverse of DA3's world-to-camera ``extrinsics``, confidence is ``1 - 1/depth_conf``, the
local points' z is the depth. Tolerances (the issue's, fp32): poses and K/V atol 1e-5, depth
atol 1e-4 + rtol 1e-5, confidence atol 1e-5.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from kvtracker_sdk.backends.onnx import OnnxBackend
from kvtracker_sdk.backends.onnx_manifest import read_manifest
from kvtracker_sdk.backends.onnx_runtime import OnnxRunner
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.errors import BackendMismatchError
from kvtracker_sdk.geometry.se3 import invert_rigid
from kvtracker_sdk.models.da3 import sdk_outputs
from kvtracker_sdk.models.da3.camera import decode_pose_encoding
from kvtracker_sdk.types import HeadSet
from tests.helpers import shared_path

GLOBAL_BLOCKS = (5, 7, 9, 11)
H, W = 98, 196  # not the export's check size (126 x 168) nor the golden one (112 x 154)


def golden(name: str) -> dict[str, np.ndarray]:
    path = shared_path("golden", "da3", f"{name}.safetensors")
    return {key: value.numpy() for key, value in load_file(path).items()}


@pytest.fixture(scope="module")
def runner(golden_da3_onnx_dir: Path) -> OnnxRunner:
    return OnnxRunner(golden_da3_onnx_dir, read_manifest(golden_da3_onnx_dir), threads=1)


def T_world_cam(extrinsics: np.ndarray) -> np.ndarray:
    """DA3's world-to-camera [..., 3, 4] -> camera-to-world [..., 4, 4]."""
    bottom = np.broadcast_to([0.0, 0.0, 0.0, 1.0], (*extrinsics.shape[:-2], 1, 4))
    return invert_rigid(np.concatenate((extrinsics.astype(np.float64), bottom), axis=-2))


def assert_matches_golden(
    poses: np.ndarray,
    confidence: np.ndarray | None,
    points: np.ndarray | None,
    expected: dict[str, np.ndarray],
    prefix: str,
) -> None:
    """[F, ...] SDK outputs against golden [1, F, ...] DA3 outputs named ``prefix + output``."""
    np.testing.assert_allclose(poses, T_world_cam(expected[prefix + "extrinsics"][0]), atol=1e-5)
    assert confidence is not None and points is not None
    depth_conf = expected[prefix + "depth_conf"][0]
    np.testing.assert_allclose(confidence, 1.0 - 1.0 / depth_conf, atol=1e-5, rtol=0)
    depth = expected[prefix + "depth"][0]
    np.testing.assert_allclose(points[..., 2], depth, atol=1e-4, rtol=1e-5)


def test_reference_pinned_mapping_pass_and_its_kv(runner: OnnxRunner) -> None:
    imgs = golden("inputs")["imgs_01"]
    outputs, keys, values = runner.map(imgs[0, :3])
    expected = golden("outputs_query")
    assert expected["keyframes.ref_view_index"].tolist() == [0]  # keyframe 0 is the reference
    assert_matches_golden(
        outputs.poses, outputs.confidence, outputs.local_points, expected, "keyframes."
    )
    kv = golden("kv_cache")
    assert runner.manifest.cache_layout.block_indices == GLOBAL_BLOCKS
    for layer, block in enumerate(GLOBAL_BLOCKS):
        np.testing.assert_allclose(keys[layer], kv[f"layer{block}.k"], atol=1e-5, rtol=0)
        np.testing.assert_allclose(values[layer], kv[f"layer{block}.v"], atol=1e-5, rtol=0)


def cache_of(runner: OnnxRunner, keys: list[np.ndarray], values: list[np.ndarray]) -> KVCache:
    return KVCache.from_layers(
        [torch.from_numpy(k) for k in keys],
        [torch.from_numpy(v) for v in values],
        layout=runner.manifest.cache_layout,
        tokens_per_frame=89,
        keyframe_ids=range(3),
    )


def test_cached_query_and_the_negative_controls(runner: OnnxRunner) -> None:
    imgs = golden("inputs")["imgs_01"]
    _, keys, values = runner.map(imgs[0, :3])
    cache = cache_of(runner, keys, values)
    assert cache.capacity > cache.length  # scratch tokens after the cache: the graph ignores them
    past = [(k.numpy(), v.numpy()) for k, v in map(cache.buffers, range(4))]
    for key, value in past:
        key[:, :, cache.length :] = np.nan
        value[:, :, cache.length :] = np.nan
    tracked = runner.track(imgs[0, 3:4], past, cache.length, HeadSet.ALL)
    expected = golden("outputs_query")
    assert_matches_golden(
        tracked.poses, tracked.confidence, tracked.local_points, expected, "query."
    )
    # the query got the non-reference camera token and read the cache: far from both controls
    for control in ("neg_single_frame", "neg_query_as_reference"):
        pose_enc = torch.from_numpy(expected[f"{control}.pose_enc"][0])
        _, intrinsics = decode_pose_encoding(pose_enc, (112, 154))
        control_pose = sdk_outputs(pose_enc, intrinsics).T_world_cam.numpy()
        assert np.abs(tracked.poses - control_pose).max() > 0.1, control


@pytest.mark.parametrize("heads", list(HeadSet))
def test_head_sets_run_the_head_graphs_they_need(runner: OnnxRunner, heads: HeadSet) -> None:
    imgs = golden("inputs")["imgs_01"]
    _, keys, values = runner.map(imgs[0, :3])
    past = list(zip(keys, values, strict=True))
    tracked = runner.track(imgs[0, 3:4], past, keys[0].shape[2], heads)
    camera_only = runner.track(imgs[0, 3:4], past, keys[0].shape[2], HeadSet.CAMERA)
    np.testing.assert_array_equal(tracked.poses, camera_only.poses)
    assert (tracked.confidence is None) == (heads is HeadSet.CAMERA)  # DualDPT gives it
    assert (tracked.local_points is None) == (heads is not HeadSet.ALL)


# ---------------------------------------------------------------- OnnxBackend
@pytest.fixture(scope="module")
def onnx_backend(golden_da3_onnx_dir: Path) -> OnnxBackend:
    return OnnxBackend(golden_da3_onnx_dir, threads=1)


@pytest.fixture(scope="module")
def images() -> np.ndarray:
    return np.random.default_rng(3).integers(0, 256, size=(4, H, W, 3), dtype=np.uint8)


def test_a_pi3_cache_is_refused(
    onnx_backend: OnnxBackend, golden_onnx_dir: Path, images: np.ndarray
) -> None:
    pi3_map = OnnxBackend(golden_onnx_dir, threads=1).map(images[:2])
    with pytest.raises(BackendMismatchError, match="layout"):
        onnx_backend.track(images[3], pi3_map.cache)

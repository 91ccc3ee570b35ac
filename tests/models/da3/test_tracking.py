"""DA3 tracking pass: head selection, batched queries, cache growth, typed errors."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch

from kvtracker_sdk.cache.kv_cache import CacheLayout, KVCache
from kvtracker_sdk.errors import CacheError, ImageShapeError, InputError
from kvtracker_sdk.models.da3 import DepthAnything3
from kvtracker_sdk.types import HeadSet
from tests.models.da3.factories import random_da3
from tests.models.da3.test_golden_parity import cache_from_map

Golden = Callable[[str], dict[str, torch.Tensor]]


@torch.no_grad()
def test_camera_only_skips_the_depth_head(golden_model: DepthAnything3, golden: Golden) -> None:
    imgs = golden("inputs")["imgs_01"]
    cache = cache_from_map(golden_model, imgs[:, :3])
    query = imgs[0, 3:4]
    calls: list[int] = []
    handle = golden_model.head.register_forward_hook(lambda *_: calls.append(1))
    try:
        camera = golden_model.forward_track(query, cache, heads=HeadSet.CAMERA)
        assert calls == []  # DualDPT never ran
        confidence = golden_model.forward_track(query, cache, heads=HeadSet.CONFIDENCE)
        assert calls == [1]
    finally:
        handle.remove()
    assert camera.depth is None and camera.depth_conf is None and camera.ray is None
    assert (
        confidence.depth is not None
        and confidence.depth_conf is not None
        and confidence.ray is None
    )
    # the camera path is the same computation whatever else is requested: bit-identical
    assert torch.equal(camera.pose_enc, confidence.pose_enc)
    assert torch.equal(camera.extrinsics, confidence.extrinsics)


@torch.no_grad()
def test_batched_queries_equal_single_queries(golden_model: DepthAnything3, golden: Golden) -> None:
    imgs = golden("inputs")["imgs_01"]
    cache = cache_from_map(golden_model, imgs[:, :2])
    queries = torch.cat([imgs[0, 2:4], torch.flip(imgs[0, 3:4], dims=[-1])])  # 3 views
    batched = golden_model.forward_track(queries, cache, heads=HeadSet.CONFIDENCE)
    assert batched.pose_enc.shape == (3, 1, 9) and batched.depth is not None
    assert batched.depth.shape == (3, 1, 112, 154)
    for index in range(3):
        single = golden_model.forward_track(
            queries[index : index + 1], cache, heads=HeadSet.CONFIDENCE
        )
        torch.testing.assert_close(batched.pose_enc[index], single.pose_enc[0], atol=1e-5, rtol=0)
        torch.testing.assert_close(batched.depth[index], single.depth[0], atol=1e-4, rtol=1e-5)  # type: ignore[index]


@torch.no_grad()
def test_tracking_grows_a_full_cache_and_keeps_it() -> None:
    model = random_da3(seed=1)
    imgs = torch.rand(1, 3, 3, 28, 42)
    cache = cache_from_map(model, imgs[:, :2])
    before = cache.clone()
    batch = imgs[0, 2:].expand(4, -1, -1, -1)  # 4 query views need more scratch than 2 spare frames
    output = model.forward_track(batch, cache)
    assert cache.capacity >= cache.length + 4 * cache.tokens_per_frame
    assert cache.equals(before)
    torch.testing.assert_close(output.pose_enc[1:], output.pose_enc[:1].expand(3, -1, -1))


@torch.no_grad()
def test_mapping_pins_the_reference_to_keyframe_zero() -> None:
    model = random_da3(seed=5)
    imgs = torch.rand(1, 4, 3, 28, 28)
    mapped = model.forward_map(imgs, heads=HeadSet.CAMERA)
    assert mapped.output.reference_view is not None and mapped.output.reference_view.tolist() == [0]
    first = model(imgs, heads=HeadSet.CAMERA, ref_view_strategy="first")
    assert torch.equal(mapped.output.pose_enc, first.pose_enc)
    # with another reference the world frame moves: the poses differ
    middle = model(imgs, heads=HeadSet.CAMERA, ref_view_strategy="middle")
    assert middle.reference_view is not None and middle.reference_view.tolist() == [2]
    assert float((middle.pose_enc - first.pose_enc).abs().max()) > 1e-2


@torch.no_grad()
def test_autocast_reaches_only_the_backbone(golden_model: DepthAnything3, golden: Golden) -> None:
    imgs = golden("inputs")["imgs_01"]
    with torch.autocast("cpu", dtype=torch.bfloat16):
        output = golden_model(imgs)
    assert output.pose_enc.dtype == torch.float32 and output.depth is not None
    assert output.depth.dtype == torch.float32
    expected = golden("outputs")
    torch.testing.assert_close(output.extrinsics, expected["extrinsics"], atol=5e-2, rtol=0)


def test_typed_errors() -> None:
    model = random_da3(seed=2)
    backbone = model.backbone
    good_layout = CacheLayout(backbone.global_block_indices, backbone.num_heads, backbone.head_dim)
    frame = torch.rand(1, 3, 28, 28)
    with pytest.raises(ImageShapeError, match=r"\[F, 3, H, W\]"):
        model.forward_track(frame[0], KVCache(good_layout, 5))
    with pytest.raises(ImageShapeError, match=r"\[B, N, 3, H, W\]"):
        model(frame)
    with pytest.raises(ImageShapeError, match="multiple of the patch size"):
        model(torch.rand(1, 1, 3, 28, 30))
    with pytest.raises(InputError, match="both extrinsics and intrinsics"):
        model(frame.unsqueeze(0), extrinsics=torch.eye(4).expand(1, 1, 4, 4))
    wrong_heads = CacheLayout(
        good_layout.block_indices, backbone.num_heads * 2, backbone.head_dim // 2
    )
    with pytest.raises(CacheError, match="does not fit"):
        model.forward_track(frame, KVCache(wrong_heads, 5))
    with pytest.raises(CacheError, match="bfloat16"):
        model.forward_track(frame, KVCache(good_layout, 5, dtype=torch.bfloat16))
    too_few = CacheLayout(good_layout.block_indices[:1], backbone.num_heads, backbone.head_dim)
    with pytest.raises(CacheError, match="has no layer 1"):
        model.forward_track(frame, KVCache(too_few, 5))

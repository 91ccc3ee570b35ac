"""Tracking pass behaviour: head selection, cache growth, typed errors on bad input or caches."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch

from kvtracker_sdk.cache.kv_cache import CacheLayout, KVCache
from kvtracker_sdk.errors import CacheError, ImageShapeError
from kvtracker_sdk.models.pi3 import Pi3
from kvtracker_sdk.types import HeadSet
from tests.models.pi3.factories import random_pi3
from tests.models.pi3.test_golden_parity import cache_from_map

Golden = Callable[..., dict[str, torch.Tensor]]


@torch.no_grad()
def test_camera_only_gives_the_same_pose(golden_model: Pi3, golden: Golden) -> None:
    imgs = golden("case2", "inputs")["imgs"]
    cache = cache_from_map(golden_model, imgs[:, :5])
    query = imgs[0, 5:6]
    camera = golden_model.forward_track(query, cache, heads=HeadSet.CAMERA)
    confidence = golden_model.forward_track(query, cache, heads=HeadSet.CONFIDENCE)
    everything = golden_model.forward_track(query, cache, heads=HeadSet.ALL)
    assert camera.conf is None and camera.points is None and camera.local_points is None
    assert confidence.conf is not None and confidence.points is None
    # the camera path is the same computation whatever else is requested: bit-identical
    assert torch.equal(camera.camera_poses, everything.camera_poses)
    assert torch.equal(confidence.camera_poses, everything.camera_poses)
    assert torch.equal(confidence.conf, everything.conf)


@torch.no_grad()
def test_appending_keyframes_and_capacity_do_not_change_results(
    golden_model: Pi3, golden: Golden
) -> None:
    imgs = golden("case2", "inputs")["imgs"]
    mapped = golden_model.forward_map(imgs[:, :5])
    tokens = mapped.tokens_per_frame
    layout = CacheLayout(golden_model.decoder.global_block_indices, 2, 32)
    roomy = KVCache.from_layers(
        mapped.keys,
        mapped.values,
        layout=layout,
        tokens_per_frame=tokens,
        keyframe_ids=range(5),
        spare_frames=20,
    )
    # start from keyframe 0 with one spare frame and append 1..4: the buffers must grow twice
    grown = KVCache.from_layers(
        [k[:, :, :tokens] for k in mapped.keys],
        [v[:, :, :tokens] for v in mapped.values],
        layout=layout,
        tokens_per_frame=tokens,
        keyframe_ids=[0],
        spare_frames=1,
    )
    initial_capacity = grown.capacity
    for frame in range(1, 5):
        window = slice(frame * tokens, (frame + 1) * tokens)
        grown.append_keyframe(
            [k[:, :, window] for k in mapped.keys], [v[:, :, window] for v in mapped.values], frame
        )
    assert grown.capacity > initial_capacity and grown.capacity != roomy.capacity
    query = torch.cat([imgs[0, 5:6], torch.flip(imgs[0, 5:6], dims=[-1])])
    a = golden_model.forward_track(query, roomy, heads=HeadSet.ALL)
    b = golden_model.forward_track(query, grown, heads=HeadSet.ALL)
    torch.testing.assert_close(a.camera_poses, b.camera_poses, atol=1e-6, rtol=0)
    torch.testing.assert_close(a.points, b.points, atol=1e-5, rtol=1e-6)


@torch.no_grad()
def test_tracking_grows_a_full_cache() -> None:
    model = random_pi3(seed=1)
    imgs = torch.rand(1, 3, 3, 28, 28)
    mapped = model.forward_map(imgs[:, :2])
    layout = CacheLayout(
        model.decoder.global_block_indices, model.decoder.num_heads, model.decoder.head_dim
    )
    cache = KVCache.from_layers(
        mapped.keys,
        mapped.values,
        layout=layout,
        tokens_per_frame=mapped.tokens_per_frame,
        keyframe_ids=[0, 1],
    )
    before = cache.clone()
    batch = imgs[0, 2:].expand(
        4, -1, -1, -1
    )  # 4 query frames need more scratch than 2 spare frames
    output = model.forward_track(batch, cache)
    assert cache.capacity >= cache.length + 4 * cache.tokens_per_frame
    assert cache.equals(before)
    torch.testing.assert_close(
        output.camera_poses[1:], output.camera_poses[:1].expand(3, -1, -1, -1)
    )


def test_typed_errors() -> None:
    model = random_pi3(seed=2)
    good_layout = CacheLayout(
        model.decoder.global_block_indices, model.decoder.num_heads, model.decoder.head_dim
    )
    frame = torch.rand(1, 3, 28, 28)
    with pytest.raises(ImageShapeError, match=r"\[F, 3, H, W\]"):
        model.forward_track(frame[0], KVCache(good_layout, 9))
    with pytest.raises(ImageShapeError, match=r"\[B, N, 3, H, W\]"):
        model(frame)
    with pytest.raises(ImageShapeError, match="multiple of the patch size"):
        model(torch.rand(1, 1, 3, 28, 30))
    wrong_heads = CacheLayout(
        good_layout.block_indices, model.decoder.num_heads * 2, model.decoder.head_dim // 2
    )
    with pytest.raises(CacheError, match="does not fit"):
        model.forward_track(frame, KVCache(wrong_heads, 9))
    with pytest.raises(CacheError, match="bfloat16"):
        model.forward_track(frame, KVCache(good_layout, 9, dtype=torch.bfloat16))
    too_few = CacheLayout(
        good_layout.block_indices[:1], model.decoder.num_heads, model.decoder.head_dim
    )
    with pytest.raises(CacheError, match="has no layer 1"):
        model.forward_track(frame, KVCache(too_few, 9))

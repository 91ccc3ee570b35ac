"""bf16 path: what is cast, and that it is as accurate as the official autocast recipe.

The official recipe is ``torch.autocast('cpu', torch.bfloat16)`` over the fp32 model (the heads
and camera modules with autocast off). The SDK's ``set_precision(torch.bfloat16)`` must deviate
from fp32 no more than it (median and worst), in the mapping pass and in tracking, for the
world-to-camera extrinsics and depth: on the golden model and on 8 random small architectures
(seeded sizes, widths, keyframe counts). On CPU it is bit-equal to autocast.

Golden model, bf16 mapping + cached query vs the fp32 golden query: pose_enc <= 5e-3,
extrinsics <= 6e-3 abs; intrinsics, depth, depth_conf <= 0.6 % relative. The tolerances below keep
the earlier, looser bounds (2e-2 abs, 2 % relative).
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import pytest
import torch

from kvtracker_sdk.cache.kv_cache import CacheLayout, KVCache
from kvtracker_sdk.models.da3 import DepthAnything3
from kvtracker_sdk.types import HeadSet
from tests.models.bf16_deviation import (
    absolute,
    assert_as_accurate_as_autocast,
    relative,
)
from tests.models.da3.factories import random_da3, tiny_config
from tests.models.da3.test_golden_parity import cache_from_map

Golden = Callable[[str], dict[str, torch.Tensor]]
POSE_ATOL, RELATIVE = 2e-2, 2e-2
MEASURES = {
    "map.extrinsics": absolute,
    "map.depth": relative,
    "track.extrinsics": absolute,
    "track.depth": relative,
}


@pytest.fixture(scope="module")
def bf16_model(golden_model: DepthAnything3) -> DepthAnything3:
    return copy.deepcopy(golden_model).set_precision(torch.bfloat16)


def test_set_precision_casts_only_matmul_weights(bf16_model: DepthAnything3) -> None:
    assert bf16_model.compute_dtype == torch.bfloat16
    vit = bf16_model.backbone.pretrained
    block = vit.blocks[5]
    for linear in (block.attn.qkv, block.attn.proj, block.mlp.fc1, block.mlp.fc2):
        assert linear.weight.dtype == linear.bias.dtype == torch.bfloat16
    assert vit.patch_embed.proj.weight.dtype == torch.bfloat16
    # the residual stream's parameters stay fp32: norms, LayerScales, embeddings, tokens
    for param in (block.norm1.weight, block.attn.k_norm.weight, block.ls1.gamma, vit.pos_embed,
                  vit.camera_token, vit.norm.weight):  # fmt: skip
        assert param.dtype == torch.float32
    for module in (bf16_model.head, bf16_model.cam_dec, bf16_model.cam_enc):
        assert all(p.dtype == torch.float32 for p in module.parameters())
    restored = copy.deepcopy(bf16_model).set_precision(torch.float32)
    assert all(p.dtype == torch.float32 for p in restored.parameters())


def _map_and_track(
    model: DepthAnything3, imgs: torch.Tensor, keyframes: int
) -> dict[str, torch.Tensor]:
    """Map views [:keyframes] (reference view 0), track view ``keyframes`` against that map."""
    mapped = model.forward_map(imgs[:, :keyframes], heads=HeadSet.CONFIDENCE)
    backbone = model.backbone
    layout = CacheLayout(backbone.global_block_indices, backbone.num_heads, backbone.head_dim)
    cache = KVCache.from_layers(mapped.keys, mapped.values, layout=layout,
                                tokens_per_frame=mapped.tokens_per_frame,
                                keyframe_ids=range(keyframes))  # fmt: skip
    query = imgs[0, keyframes : keyframes + 1]
    tracked = model.forward_track(query, cache, heads=HeadSet.CONFIDENCE)
    assert mapped.output.depth is not None and tracked.depth is not None
    return {
        "map.extrinsics": mapped.output.extrinsics,
        "map.depth": mapped.output.depth,
        "track.extrinsics": tracked.extrinsics,
        "track.depth": tracked.depth,
    }


def _assert_as_accurate_as_autocast(
    model: DepthAnything3, imgs: torch.Tensor, keyframes: int, label: str
) -> None:
    run = lambda network: _map_and_track(network, imgs, keyframes)  # noqa: E731
    assert_as_accurate_as_autocast(model, run, MEASURES, label)


def test_bf16_as_accurate_as_autocast_on_golden(
    golden_model: DepthAnything3, golden: Golden
) -> None:
    _assert_as_accurate_as_autocast(golden_model, golden("inputs")["imgs_01"], 3, "golden")


@pytest.mark.parametrize("seed", range(8))
def test_bf16_as_accurate_as_autocast_on_random_models(seed: int) -> None:
    draw = torch.Generator().manual_seed(seed)

    def pick(*options: int) -> int:
        return options[int(torch.randint(len(options), (1,), generator=draw))]

    heads = pick(2, 4)
    model = random_da3(tiny_config(dim=8 * heads * pick(1, 2), heads=heads), seed=seed)
    keyframes = pick(1, 2, 3)
    imgs = torch.rand(1, keyframes + 1, 3, 14 * pick(2, 3, 5), 14 * pick(2, 4), generator=draw)
    _assert_as_accurate_as_autocast(model, imgs, keyframes, f"seed {seed}")


@torch.no_grad()
def test_bf16_tracking_close_to_fp32(bf16_model: DepthAnything3, golden: Golden) -> None:
    imgs = golden("inputs")["imgs_01"]
    cache = cache_from_map(bf16_model, imgs[:, :3])
    assert cache.dtype == torch.bfloat16
    output = bf16_model.forward_track(imgs[0, 3:4], cache, heads=HeadSet.CONFIDENCE)
    expected = golden("outputs_query")
    assert output.pose_enc.dtype == torch.float32 and output.depth is not None
    for name in ("pose_enc", "extrinsics"):
        torch.testing.assert_close(
            getattr(output, name), expected[f"query.{name}"], atol=POSE_ATOL, rtol=0
        )
    for name in ("intrinsics", "depth", "depth_conf"):
        torch.testing.assert_close(
            getattr(output, name), expected[f"query.{name}"], atol=0, rtol=RELATIVE
        )
    # and bf16 is really in use: it is not bit-equal to fp32
    assert float((output.pose_enc - expected["query.pose_enc"]).abs().max()) > 1e-5

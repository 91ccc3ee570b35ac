"""bf16 path: what is cast, and how far it lands from the fp32 golden outputs.

Measured on the golden reduced model (random weights, CPU, torch 2.13), bf16 mapping + cached
query vs the fp32 golden query: pose_enc <= 7.6e-3, extrinsics <= 9.7e-3 abs; intrinsics <=
0.7 %, depth <= 0.9 %, depth_conf <= 0.7 % relative. The tolerances below leave a 2x margin.
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import pytest
import torch

from kvtracker_sdk.models.da3 import DepthAnything3
from kvtracker_sdk.types import HeadSet
from tests.models.da3.test_golden_parity import cache_from_map

Golden = Callable[[str], dict[str, torch.Tensor]]
POSE_ATOL, RELATIVE = 2e-2, 2e-2


@pytest.fixture(scope="module")
def bf16_model(golden_model: DepthAnything3) -> DepthAnything3:
    return copy.deepcopy(golden_model).set_precision(torch.bfloat16)


def test_set_precision_keeps_heads_in_fp32(bf16_model: DepthAnything3) -> None:
    assert bf16_model.compute_dtype == torch.bfloat16
    vit = bf16_model.backbone.pretrained
    assert (
        vit.pos_embed.dtype == torch.bfloat16
        and vit.blocks[5].attn.k_norm.weight.dtype == torch.bfloat16
    )
    for module in (bf16_model.head, bf16_model.cam_dec, bf16_model.cam_enc):
        assert all(p.dtype == torch.float32 for p in module.parameters())


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

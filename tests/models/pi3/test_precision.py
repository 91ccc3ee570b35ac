"""bf16 path: what is cast, and how far it lands from fp32 on the golden model.

Measured on the golden reduced model (random weights, CPU, torch 2.13), bf16 tracking vs the fp32
golden queries: pose entries <= 1.4e-2, sigmoid(conf) <= 2.5e-2, median relative point error
<= 1.5e-2. (The full 6-frame forward of case2 differs by up to 0.08 in pose entries; CPU bf16
autocast of the fp32 model — close to the official CUDA path — differs by 0.03 there.) The
tolerances below leave a 2x margin.
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import pytest
import torch

from kvtracker_sdk.models.pi3 import Pi3
from kvtracker_sdk.types import HeadSet
from tests.models.pi3.test_golden_parity import CASES, cache_from_map, query_image

Golden = Callable[..., dict[str, torch.Tensor]]
POSE_ATOL, CONF_ATOL, POINTS_MEDIAN_REL = 3e-2, 5e-2, 3e-2


@pytest.fixture(scope="module")
def bf16_model(golden_model: Pi3) -> Pi3:
    return copy.deepcopy(golden_model).set_precision(torch.bfloat16)


def test_set_precision_keeps_final_heads_in_fp32(bf16_model: Pi3) -> None:
    assert bf16_model.compute_dtype == torch.bfloat16
    assert bf16_model.encoder.pos_embed.dtype == torch.bfloat16
    assert bf16_model.decoder[1].attn.k_norm.weight.dtype == torch.bfloat16
    assert bf16_model.camera_decoder.linear_out.weight.dtype == torch.bfloat16
    for head in (bf16_model.camera_head, bf16_model.point_head, bf16_model.conf_head):
        assert all(p.dtype == torch.float32 for p in head.parameters())
    assert bf16_model.image_mean.dtype == torch.float32


@pytest.mark.parametrize("case", sorted(CASES))
@torch.no_grad()
def test_bf16_tracking_close_to_fp32(bf16_model: Pi3, golden: Golden, case: str) -> None:
    num_keyframes, queries = CASES[case]
    imgs = golden(case, "inputs")["imgs"]
    cache = cache_from_map(bf16_model, imgs[:, :num_keyframes])
    assert cache.dtype == torch.bfloat16
    expected = golden(case, "outputs_query")
    for name in queries:
        output = bf16_model.forward_track(
            query_image(imgs, num_keyframes, name), cache, heads=HeadSet.ALL
        )
        assert output.camera_poses.dtype == torch.float32 and output.points is not None
        torch.testing.assert_close(
            output.camera_poses, expected[f"{name}.camera_poses"], atol=POSE_ATOL, rtol=0
        )
        conf = torch.sigmoid(output.conf)  # type: ignore[arg-type]
        torch.testing.assert_close(
            conf, torch.sigmoid(expected[f"{name}.conf"]), atol=CONF_ATOL, rtol=0
        )
        reference = expected[f"{name}.points"]
        relative = (output.points - reference).norm(dim=-1) / reference.norm(dim=-1)
        assert float(relative.median()) < POINTS_MEDIAN_REL
        # and bf16 is really in use: it is not bit-equal to fp32
        assert float((output.camera_poses - expected[f"{name}.camera_poses"]).abs().max()) > 1e-5


@torch.no_grad()
def test_cpu_autocast_runs_with_fp32_heads(golden_model: Pi3, golden: Golden) -> None:
    imgs = golden("case1", "inputs")["imgs"]
    with torch.autocast("cpu", dtype=torch.bfloat16):
        output = golden_model(imgs)
    assert output.camera_poses.dtype == torch.float32 and output.points.dtype == torch.float32  # type: ignore[union-attr]
    rotations = output.camera_poses[0, :, :3, :3]
    torch.testing.assert_close(torch.linalg.det(rotations), torch.ones(4), atol=1e-5, rtol=0)
    expected = golden("case1", "outputs")["camera_poses"]
    torch.testing.assert_close(output.camera_poses, expected, atol=POSE_ATOL, rtol=0)

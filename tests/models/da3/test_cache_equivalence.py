"""Property: DA3 tracking through the KV cache equals the full forward under the keyframe/query mask.

For random small DA3 architectures (widths, depth, ``alt_start``, out layers, DPT widths), grid
sizes and keyframe counts, the reference is the full model on [keyframes, queries] with
``keyframe_query_mask`` in its global blocks and the reference view pinned to view 0 (keyframe 0);
there every query carries the non-reference camera token. The mapping pass on the keyframes
(its K/V in a ``KVCache``) followed by the tracking pass must reproduce the queries' outputs,
one query at a time and all queries batched. Tracking against an empty cache must not (the
control that shows the test can fail).

Tolerances (fp32): pose encodings (translation, quaternion, field of view) atol 1e-4; depth and
confidence atol 1e-4 + rtol 1e-4. Intrinsics are not compared: they are a function of the field
of view whose relative error grows as 1/fov, so random weights with tiny fields of view make them
a poor test of the cache. The empty-cache control must fail that same comparison.
"""

from __future__ import annotations

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.models.da3 import (
    DA3BackboneConfig,
    DA3CameraEncoderConfig,
    DA3Config,
    DA3HeadConfig,
    DA3Output,
    DepthAnything3,
)
from kvtracker_sdk.models.layers.attention import keyframe_query_mask
from kvtracker_sdk.types import HeadSet
from tests.models.da3.factories import randomise_
from tests.models.da3.test_golden_parity import cache_from_map

MAPS = ("depth", "depth_conf")


@st.composite
def scenarios(draw: st.DrawFn) -> dict[str, object]:
    heads = draw(st.sampled_from([1, 2]))
    dim = heads * draw(st.sampled_from([4, 8, 12]))
    depth = draw(st.integers(4, 7))
    # alt_start must leave at least one odd (global) block below depth
    alt_start = draw(
        st.integers(1, depth - 1).filter(lambda a: any(i % 2 for i in range(a, depth)))
    )
    # the last out layer is the last block, so every output depends on some global block
    out_layers = (
        *sorted(draw(st.sets(st.integers(0, depth - 2), min_size=3, max_size=3))),
        depth - 1,
    )
    features = draw(st.sampled_from([8, 16]))
    config = DA3Config(
        backbone=DA3BackboneConfig(
            embed_dim=dim,
            depth=depth,
            num_heads=heads,
            alt_start=alt_start,
            out_layers=out_layers,  # type: ignore[arg-type]
            pos_embed_grid=draw(st.integers(2, 5)),
        ),
        head=DA3HeadConfig(
            features=features, out_channels=tuple(draw(st.sampled_from([4, 8])) for _ in range(4))
        ),  # type: ignore[arg-type]
        cam_enc=DA3CameraEncoderConfig(depth=1, num_heads=heads),
    )
    return {
        "config": config,
        "grid": (draw(st.integers(1, 3)), draw(st.integers(1, 3))),
        "keyframes": draw(st.integers(1, 4)),
        "queries": draw(st.integers(1, 3)),
        "seed": draw(st.integers(0, 2**16)),
    }


def _view(output: DA3Output, batch: int, view: int) -> dict[str, torch.Tensor]:
    names = ("pose_enc", *MAPS)
    return {name: getattr(output, name)[batch, view] for name in names}


def _close(got: dict[str, torch.Tensor], expected: dict[str, torch.Tensor]) -> None:
    torch.testing.assert_close(got["pose_enc"], expected["pose_enc"], atol=1e-4, rtol=0)
    for name in MAPS:
        torch.testing.assert_close(got[name], expected[name], atol=1e-4, rtol=1e-4, msg=name)


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenarios())
@torch.no_grad()
def test_tracking_equals_masked_forward(scenario: dict[str, object]) -> None:
    config: DA3Config = scenario["config"]  # type: ignore[assignment]
    grid_h, grid_w = scenario["grid"]  # type: ignore[misc]
    num_keyframes: int = scenario["keyframes"]  # type: ignore[assignment]
    num_queries: int = scenario["queries"]  # type: ignore[assignment]
    seed: int = scenario["seed"]  # type: ignore[assignment]
    torch.manual_seed(seed)
    model = randomise_(DepthAnything3(config), seed)
    imgs = torch.rand(1, num_keyframes + num_queries, 3, 14 * grid_h, 14 * grid_w)
    tokens = model.tokens_per_frame(14 * grid_h, 14 * grid_w)
    mask = keyframe_query_mask(num_keyframes * tokens, num_queries, tokens)
    reference = model(imgs, ref_view_strategy="first", global_attn_mask=mask)
    queries = imgs[0, num_keyframes:]

    cache = cache_from_map(model, imgs[:, :num_keyframes])
    for index in range(num_queries):  # one query at a time
        tracked = model.forward_track(queries[index : index + 1], cache, heads=HeadSet.ALL)
        _close(_view(tracked, 0, 0), _view(reference, 0, num_keyframes + index))

    batched = model.forward_track(queries, cache, heads=HeadSet.ALL)  # all queries in one pass
    for index in range(num_queries):
        _close(_view(batched, index, 0), _view(reference, 0, num_keyframes + index))

    # control: without the keyframes' K/V the query is a different computation, and the same
    # comparison must say so
    empty = KVCache(cache.layout, cache.tokens_per_frame, capacity_frames=1)
    alone = model.forward_track(queries[:1], empty, heads=HeadSet.ALL)
    with pytest.raises(AssertionError):
        _close(_view(alone, 0, 0), _view(reference, 0, num_keyframes))

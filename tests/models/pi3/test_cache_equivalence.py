"""Property: tracking through the KV cache equals the full forward under the keyframe/query mask.

For random small architectures, grid sizes and keyframe counts, the full model on
[keyframes, queries] with ``keyframe_query_mask`` in its global blocks is the reference; the
mapping pass on the keyframes (its K/V in a ``KVCache``) followed by the tracking pass on the
queries must reproduce the queries' outputs, alone or batched. Tracking with an empty cache must
not (the control that shows the test can fail).

Tolerances (fp32): poses atol 1e-4; conf and points 1e-4 relative to the output's largest
magnitude (random weights give depths up to ~1e3 through exp, and x = u * exp(d) scales the error
of u by z even where x is small). Measured: below 1e-6 relative. The cache-dropped control differs
by more than 1e-2 absolute.
"""

from __future__ import annotations

import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kvtracker_sdk.cache.kv_cache import CacheLayout, KVCache
from kvtracker_sdk.models.layers.attention import keyframe_query_mask
from kvtracker_sdk.models.pi3 import (
    Pi3,
    Pi3Config,
    Pi3DecoderConfig,
    Pi3EncoderConfig,
    Pi3HeadsConfig,
    Pi3Output,
)
from kvtracker_sdk.types import HeadSet
from tests.models.pi3.factories import randomise_


@st.composite
def scenarios(draw: st.DrawFn) -> dict[str, object]:
    heads = draw(st.sampled_from([1, 2, 4]))
    dim = heads * draw(st.sampled_from([4, 8, 12]))
    head_heads = draw(st.sampled_from([1, 2]))
    config = Pi3Config(
        encoder=Pi3EncoderConfig(
            embed_dim=dim,
            depth=draw(st.integers(1, 2)),
            num_heads=heads,
            num_register_tokens=draw(st.integers(0, 4)),
            pos_embed_grid=draw(st.integers(3, 6)),
        ),
        decoder=Pi3DecoderConfig(
            embed_dim=dim,
            depth=draw(st.sampled_from([2, 4, 6])),
            num_heads=heads,
            num_register_tokens=draw(st.integers(1, 5)),
        ),
        heads=Pi3HeadsConfig(
            embed_dim=head_heads * draw(st.sampled_from([4, 8])),
            depth=draw(st.integers(1, 2)),
            num_heads=head_heads,
            point_out_dim=draw(st.sampled_from([8, 16])),
            camera_out_dim=draw(st.sampled_from([8, 16])),
        ),
    )
    return {
        "config": config,
        "grid": (draw(st.integers(1, 4)), draw(st.integers(1, 4))),
        "keyframes": draw(st.integers(1, 4)),
        "queries": draw(st.integers(1, 3)),
        "seed": draw(st.integers(0, 2**16)),
    }


def _cache(model: Pi3, keyframes: torch.Tensor) -> KVCache:
    mapped = model.forward_map(keyframes)
    layout = CacheLayout(
        model.decoder.global_block_indices, model.decoder.num_heads, model.decoder.head_dim
    )
    return KVCache.from_layers(
        mapped.keys,
        mapped.values,
        layout=layout,
        tokens_per_frame=mapped.tokens_per_frame,
        keyframe_ids=range(keyframes.shape[1]),
    )


def _close(got: Pi3Output, expected: Pi3Output) -> None:
    torch.testing.assert_close(got.camera_poses, expected.camera_poses, atol=1e-4, rtol=0)
    for name in ("conf", "local_points", "points"):
        reference = getattr(expected, name)
        # relative to the output's range: x = u * exp(d) turns a 1e-7 error in u into 1e-7 * max z
        atol = 1e-4 * max(1.0, float(reference.abs().max()))
        torch.testing.assert_close(getattr(got, name), reference, atol=atol, rtol=0, msg=name)


def _max_difference(a: Pi3Output, b: Pi3Output) -> float:
    names = ("camera_poses", "conf", "local_points")
    return max(float((getattr(a, n) - getattr(b, n)).abs().max()) for n in names)


def _frame(output: Pi3Output, index: int) -> Pi3Output:
    """Query ``index`` of a reference output [1, N, ...] as a tracked output [1, 1, ...]."""
    return Pi3Output(
        camera_poses=output.camera_poses[:, index : index + 1],
        conf=output.conf[:, index : index + 1],  # type: ignore[index]
        local_points=output.local_points[:, index : index + 1],  # type: ignore[index]
        points=output.points[:, index : index + 1],  # type: ignore[index]
    )


def _row(output: Pi3Output, index: int) -> Pi3Output:
    """Row ``index`` of a batched tracking output [F, 1, ...]."""
    return Pi3Output(
        camera_poses=output.camera_poses[index : index + 1],
        conf=output.conf[index : index + 1],  # type: ignore[index]
        local_points=output.local_points[index : index + 1],  # type: ignore[index]
        points=output.points[index : index + 1],  # type: ignore[index]
    )


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenarios())
@torch.no_grad()
def test_tracking_equals_masked_forward(scenario: dict[str, object]) -> None:
    config: Pi3Config = scenario["config"]  # type: ignore[assignment]
    grid_h, grid_w = scenario["grid"]  # type: ignore[misc]
    num_keyframes: int = scenario["keyframes"]  # type: ignore[assignment]
    num_queries: int = scenario["queries"]  # type: ignore[assignment]
    seed: int = scenario["seed"]  # type: ignore[assignment]
    torch.manual_seed(seed)
    model = randomise_(Pi3(config), seed)
    imgs = torch.rand(1, num_keyframes + num_queries, 3, 14 * grid_h, 14 * grid_w)
    tokens = model.tokens_per_frame(14 * grid_h, 14 * grid_w)
    mask = keyframe_query_mask(num_keyframes * tokens, num_queries, tokens)
    reference = model(imgs, global_attn_mask=mask)
    queries = imgs[0, num_keyframes:]

    cache = _cache(model, imgs[:, :num_keyframes])
    for index in range(num_queries):  # one query at a time
        tracked = model.forward_track(queries[index : index + 1], cache, heads=HeadSet.ALL)
        _close(tracked, _frame(reference, num_keyframes + index))

    batched = model.forward_track(queries, cache, heads=HeadSet.ALL)  # all queries in one pass
    for index in range(num_queries):
        _close(_row(batched, index), _frame(reference, num_keyframes + index))

    # control: without the keyframes' K/V the query is a different computation
    empty = KVCache(cache.layout, cache.tokens_per_frame, capacity_frames=1)
    alone = model.forward_track(queries[:1], empty, heads=HeadSet.ALL)
    assert _max_difference(alone, _frame(reference, num_keyframes)) > 1e-2

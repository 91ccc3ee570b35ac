"""The CUDA-graph tracking step's logic on the CPU: everything but the capture itself.

A graph replays the kernels of one eager call over the same buffers, so a runner whose "capture"
keeps the call and whose "replay" runs it again over those buffers (``ReplayingGraphs``) is the
runner minus CUDA: it checks the static cache and its key mask (garbage in unused slots must not
change a pose), the capacity ladder, loading a map once and again when it changes, the scratch
written back, the Pi3 camera head's deferred projection, and the eager fallbacks. Tolerances:
1e-5 on fp32 poses and outputs (the masked step attends over the same keys in another order of
summation), also on the query's K/V written back into the map cache's scratch.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import torch

from kvtracker_sdk.backends.cuda_graph_step import (
    GraphOptions,
    GraphTracking,
    StaticCache,
    capacity_ladder,
)
from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.cache.kv_cache import KVCache
from kvtracker_sdk.errors import CacheError, ConfigError
from kvtracker_sdk.models.registry import family_of
from kvtracker_sdk.types import HeadSet
from tests.models.da3.factories import random_da3
from tests.models.da3.factories import tiny_config as tiny_da3
from tests.models.pi3.factories import random_pi3

H, W = 28, 42
HEAD_SETS = [HeadSet.CAMERA, HeadSet.CONFIDENCE, HeadSet.ALL]


class ReplayingGraphs(GraphTracking):
    """``GraphTracking`` on the CPU: a replay re-runs the captured call and writes its result
    into the first call's output tensors, as a graph writes into its captured outputs."""

    def _supports(self, device: torch.device) -> bool:
        return True

    def _record(self, step: Callable[[], Any], device: torch.device) -> tuple[Callable[[], Any], Any]:
        output = step()

        def replay() -> None:
            _copy_into(output, step())

        return replay, output


def _copy_into(target: Any, source: Any) -> None:
    for name in vars(target):
        value = getattr(target, name)
        if isinstance(value, torch.Tensor):
            value.copy_(getattr(source, name))


def _map(model: torch.nn.Module, frames: torch.Tensor) -> KVCache:
    """The cache of a mapping pass over ``frames`` [N, 3, H, W] (keyframe ids 0..N-1)."""
    family = family_of(model)
    with torch.no_grad():
        mapped = family.map(model, frames)
    return KVCache.from_layers(
        mapped.keys, mapped.values, layout=family.cache_layout(model),
        tokens_per_frame=model.tokens_per_frame(H, W), keyframe_ids=range(frames.shape[0]),
    )  # fmt: skip


def _models() -> dict[str, torch.nn.Module]:
    return {"pi3": random_pi3(seed=3), "da3": random_da3(tiny_da3(), seed=3)}


@pytest.fixture(scope="module")
def models() -> dict[str, torch.nn.Module]:
    return _models()


@pytest.fixture(scope="module")
def frames() -> torch.Tensor:
    return torch.rand(6, 3, H, W, generator=torch.Generator().manual_seed(0))


def _assert_same(output: Any, expected: Any, atol: float = 1e-5) -> None:
    for name, value in vars(expected).items():
        if isinstance(value, torch.Tensor):
            # points: magnitudes ~100 (the golden tests allow 1e-4 relative on them too)
            torch.testing.assert_close(getattr(output, name), value, atol=atol, rtol=1e-4)
        else:
            assert getattr(output, name) is None or value is not None, name


def _largest_difference(output: Any, expected: Any) -> float:
    return max(
        float((getattr(output, name) - value).abs().max())
        for name, value in vars(expected).items()
        if isinstance(value, torch.Tensor) and value.is_floating_point()
    )


def test_capacity_ladder() -> None:
    ladder = GraphOptions(max_keyframes=50, ladder=True)
    assert [capacity_ladder(n, ladder) for n in (1, 2, 3, 8, 9, 33, 50)] == [1, 2, 4, 8, 16, 50, 50]
    assert capacity_ladder(51, ladder) is None
    flat = GraphOptions(max_keyframes=50)
    assert {capacity_ladder(n, flat) for n in (1, 7, 50)} == {50}
    with pytest.raises(ConfigError):
        GraphOptions(max_keyframes=0)


@pytest.mark.parametrize("name", ["pi3", "da3"])
@torch.no_grad()
def test_static_cache_with_garbage_tracks_like_the_cache(
    models: dict[str, torch.nn.Module], frames: torch.Tensor, name: str
) -> None:
    """The masked step over a static cache = the dynamic step; unmasked garbage would not be."""
    model = models[name]
    cache = _map(model, frames[:3])
    layout = family_of(model).cache_layout(model)
    tokens = cache.tokens_per_frame
    static = StaticCache(layout, 5 * tokens, tokens, dtype=torch.float32, device=torch.device("cpu"))
    for layer in range(layout.num_layers):  # far-off keys where no keyframe is held
        for buffer in static.buffers(layer):
            buffer.normal_(0, 30, generator=torch.Generator().manual_seed(layer))
    static.load(cache)
    query = frames[3:4]
    expected = model.forward_track(query, cache, heads=HeadSet.CONFIDENCE)
    _assert_same(model.forward_track(query, static, heads=HeadSet.CONFIDENCE), expected)
    static.set_lengths((5 * tokens,) * layout.num_layers)  # the garbage unmasked: not the same
    garbage = model.forward_track(query, static, heads=HeadSet.CONFIDENCE)
    assert _largest_difference(garbage, expected) > 1e-2


@pytest.mark.parametrize("name", ["pi3", "da3"])
@torch.no_grad()
def test_runner_follows_growing_and_new_maps(
    models: dict[str, torch.nn.Module], frames: torch.Tensor, name: str
) -> None:
    model = copy.deepcopy(models[name])
    eager = model.forward_track
    runner = ReplayingGraphs(
        model, family_of(model).cache_layout(model), GraphOptions(4, ladder=True)
    )
    query = frames[5:6]
    # capacities 1, 2, 4 (masked), 4 full (captured with the masked one), 2 again
    for keyframes in (1, 2, 3, 4, 2):
        cache = _map(model, frames[:keyframes])
        reference = cache.clone()
        for heads in HEAD_SETS:
            expected = eager(query, reference, heads=heads)
            _assert_same(runner(query, cache, heads=heads), expected)
            for layer in range(cache.layout.num_layers):  # the scratch, as the eager step left it
                end = cache.layer_length(layer) + cache.tokens_per_frame
                for ours, theirs in zip(cache.buffers(layer), reference.buffers(layer), strict=True):
                    torch.testing.assert_close(
                        ours[:, :, :end], theirs[:, :, :end], atol=1e-5, rtol=1e-5
                    )
    report = runner.report
    # rungs 1, 2 and 4 per head set, each masked and full: nothing captured for 4 or 2 again
    assert len(report.captures) == 3 * 2 * len(HEAD_SETS)
    assert report.cache_loads == 5 and report.replays == 5 * len(HEAD_SETS) and report.eager == 0

    # a map in place (a keyframe dropped) is loaded again; a map past the capacity runs eager
    cache.drop_keyframes([0])
    _assert_same(runner(query, cache, heads=HeadSet.CAMERA), eager(query, cache.clone()))
    assert report.cache_loads == 6
    large = _map(model, frames[:5])
    _assert_same(runner(query, large, heads=HeadSet.CAMERA), eager(query, large.clone()))
    assert report.eager == 1 and "5 keyframes > max_keyframes 4" in report.errors[-1]


@torch.no_grad()
def test_runner_checks_the_cache_and_falls_back(
    models: dict[str, torch.nn.Module], frames: torch.Tensor
) -> None:
    model = copy.deepcopy(models["pi3"])
    runner = ReplayingGraphs(model, family_of(model).cache_layout(model), GraphOptions(4))
    cache = _map(model, frames[:2])
    with pytest.raises(CacheError):  # the model computes in fp32: the caller's error, not ours
        runner(frames[5:6], cache.to(dtype=torch.bfloat16))
    assert runner.report.eager == 0 and not runner.report.errors
    runner(frames[4:6], cache)  # two query frames: eager
    assert runner.report.eager == 1 and "2 query frames" in runner.report.errors[-1]
    # the real runner on the CPU never captures
    real = GraphTracking(model, family_of(model).cache_layout(model), GraphOptions(4))
    real(frames[5:6], cache)
    assert real.report.eager == 1 and "graphs are CUDA only" in real.report.errors[-1]


def test_torch_backend_option_on_cpu(models: dict[str, torch.nn.Module]) -> None:
    images = np.random.default_rng(1).integers(0, 256, size=(3, H, W, 3), dtype=np.uint8)
    plain = TorchBackend(copy.deepcopy(models["da3"]))
    graphed = TorchBackend(copy.deepcopy(models["da3"]), cuda_graph=GraphOptions(8))
    assert "cuda-graph-8" in graphed.info.accelerations
    assert graphed.info.fingerprint == plain.info.fingerprint
    mapped = plain.map(images[:2])
    expected = plain.track(images[2], mapped.cache).pose
    np.testing.assert_allclose(graphed.track(images[2], mapped.cache).pose, expected, atol=1e-6)
    assert graphed.graph_report is not None and graphed.graph_report.eager == 1
    with pytest.raises(ConfigError):
        TorchBackend(copy.deepcopy(models["da3"]), cuda_graph=True, compile=True)


@torch.no_grad()
def test_pi3_finishes_a_captured_output(
    models: dict[str, torch.nn.Module], frames: torch.Tensor
) -> None:
    """Under capture Pi3's camera head leaves the raw 3x3 (the SVD syncs the host); the finish
    projects it and recomputes the world points: the eager output again."""
    model = models["pi3"]
    expected = model.forward_track(frames[5:6], _map(model, frames[:2]), heads=HeadSet.ALL)
    raw = expected.camera_poses.clone()
    raw[..., :3, :3] *= torch.tensor([2.0, 0.5, 3.0]).view(3, 1)  # rows rescaled: the same rotation
    captured = dataclasses.replace(expected, camera_poses=raw, points=torch.zeros_like(expected.points))
    _assert_same(model.finish_captured_track(captured), expected)

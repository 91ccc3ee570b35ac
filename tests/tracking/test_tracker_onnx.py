"""A tracker session on the 20 real TUM frames: PyTorch, ONNX Runtime, OpenVINO, and live swaps.

Both families, with their golden (small, random) weights exported once per test session
(``onnx_exports``, shared with every test that needs an export; ONNX Runtime and OpenVINO serve
the same export) — Pi3 and Depth Anything 3 (``family`` parametrises the module's fixtures). The
runtimes compute the same fp32 function, so every pose agrees within 1e-4 (the issue's
tolerance) whichever backend tracked it and whichever built the map. Keyframes every 5 frames: 4
mapping passes, so maps made by one runtime are tracked and rebuilt by the other after the swap.
The swaps run onnx -> torch and a chain torch -> openvino (frame 8) -> onnx (frame 14): openvino
tracks and rebuilds a torch map, onnx tracks openvino's (the chain replaced a torch -> onnx run:
onnx on a torch map is the relocalisation's and ``test_onnx_backend_families.py``'s). A whole
OpenVINO session would add nothing these do not run.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np
import pytest

from kvtracker_sdk.backends.base import Backend
from kvtracker_sdk.backends.onnx import OnnxBackend
from kvtracker_sdk.backends.openvino import OpenVinoBackend
from kvtracker_sdk.backends.torch_backend import TorchBackend
from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.errors import BackendMismatchError
from kvtracker_sdk.tracking.facade.tracker import Tracker
from kvtracker_sdk.types import FrameResult, TrackingState
from tests.conftest import OnnxExport
from tests.helpers import dev_dependency, shared_path

CONFIG = {"resolution": 224, "keyframing": {"interval_frames": 5}}
SWAPS_AT = (8, 14)  # between keyframes: each swap keeps a map built by the runtime before


@pytest.fixture(scope="module")
def frames() -> list[tuple[float, np.ndarray]]:
    files = sorted(shared_path("data", "tum_fr2_desk", "rgb").glob("*.png"))
    assert len(files) == 20
    return [(float(f.stem), cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB)) for f in files]


@pytest.fixture(scope="module", params=["pi3", "da3"])
def family(request: pytest.FixtureRequest) -> str:
    return str(request.param)


@pytest.fixture(scope="module")
def make_torch(family: str) -> Callable[[], TorchBackend]:
    weights = shared_path("golden", family, "weights.safetensors")
    return lambda: TorchBackend.from_pretrained(weights)


@pytest.fixture(scope="module")
def make_onnx(family: str, onnx_exports: Callable[[str], OnnxExport]) -> Callable[[], OnnxBackend]:
    folder = onnx_exports(family).folder  # the session's export of the family
    return lambda: OnnxBackend(folder, threads=1)


@pytest.fixture(scope="module")
def make_openvino(
    family: str, onnx_exports: Callable[[str], OnnxExport]
) -> Callable[[], OpenVinoBackend]:
    dev_dependency("openvino")
    folder = onnx_exports(family).folder  # the same export ONNX Runtime serves
    return lambda: OpenVinoBackend(folder, threads=1)


@pytest.fixture(scope="module")
def makers(
    make_torch: Callable[[], TorchBackend],
    make_onnx: Callable[[], OnnxBackend],
    make_openvino: Callable[[], OpenVinoBackend],
) -> dict[str, Callable[[], Backend]]:
    return {"torch": make_torch, "onnx": make_onnx, "openvino": make_openvino}


@pytest.fixture(scope="module")
def make_pi3_onnx(golden_onnx_dir: Path) -> Callable[[], OnnxBackend]:
    return lambda: OnnxBackend(golden_onnx_dir, threads=1)


def run(
    frames: list[tuple[float, np.ndarray]],
    first: Backend,
    swaps: Sequence[Callable[[], Backend]] = (),
) -> tuple[list[FrameResult], list[str]]:
    """Push every frame; swap to ``swaps[i]()`` before frame ``SWAPS_AT[i]``."""
    results, runtimes = [], []
    swap_at = dict(zip(SWAPS_AT[: len(swaps)], swaps, strict=True))
    with Tracker(TrackerConfig.from_dict(CONFIG), first) as tracker:
        for index, (stamp, image) in enumerate(frames):
            if index in swap_at:
                tracker.set_backend(swap_at[index]()).close()
            results.append(tracker.push_frame(image, timestamp=stamp))
            runtimes.append(tracker.backend.info.backend)
        tracker.backend.close()
    return results, runtimes


def assert_same_poses(results: list[FrameResult], expected: list[FrameResult]) -> None:
    assert [r.keyframe_id for r in results] == [r.keyframe_id for r in expected]
    assert [r.state for r in results] == [r.state for r in expected]
    for result, reference in zip(results, expected, strict=True):
        assert result.pose is not None and reference.pose is not None
        np.testing.assert_allclose(result.pose.T_world_cam, reference.pose.T_world_cam, atol=1e-4)


@pytest.fixture(scope="module")
def torch_session(
    frames: list[tuple[float, np.ndarray]], make_torch: Callable[[], TorchBackend]
) -> list[FrameResult]:
    results, _ = run(frames, make_torch())
    assert sum(r.is_keyframe for r in results) == 4
    return results


@pytest.mark.slow
def test_onnx_session_gives_the_torch_poses(
    frames: list[tuple[float, np.ndarray]],
    make_onnx: Callable[[], OnnxBackend],
    torch_session: list[FrameResult],
) -> None:
    results, runtimes = run(frames, make_onnx())
    assert set(runtimes) == {"onnx"}
    assert results[-1].state == torch_session[-1].state
    assert_same_poses(results, torch_session)


@pytest.mark.slow
@pytest.mark.parametrize("direction", ["onnx->torch", "torch->openvino->onnx"])
def test_live_swap_keeps_the_map_and_the_poses(
    frames: list[tuple[float, np.ndarray]],
    makers: dict[str, Callable[[], Backend]],
    torch_session: list[FrameResult],
    direction: str,
) -> None:
    names = direction.split("->")
    results, runtimes = run(frames, makers[names[0]](), [makers[name] for name in names[1:]])
    bounds = (0, *SWAPS_AT[: len(names) - 1], len(frames))
    segments = zip(names, bounds, bounds[1:], strict=False)  # bounds has one more entry
    assert runtimes == [name for name, start, end in segments for _ in range(start, end)]
    assert_same_poses(results, torch_session)


def test_swap_to_other_weights_is_refused(
    frames: list[tuple[float, np.ndarray]], make_pi3_onnx: Callable[[], OnnxBackend]
) -> None:
    from tests.models.pi3.factories import random_pi3, tiny_config

    stranger = TorchBackend(random_pi3(tiny_config(dim=64, depth=8), seed=5))  # the golden layout
    with Tracker(TrackerConfig.from_dict(CONFIG), make_pi3_onnx()) as tracker:
        tracker.push_frame(frames[0][1], timestamp=frames[0][0])
        assert stranger.info.layout == tracker.backend.info.layout
        with pytest.raises(BackendMismatchError, match="fingerprint"):
            tracker.set_backend(stranger)
        assert tracker.backend.info.backend == "onnx"  # unchanged, and still tracking
        assert tracker.push_frame(frames[1][1], timestamp=frames[1][0]).pose_valid
        tracker.backend.close()


@pytest.mark.slow
def test_a_map_saved_on_one_runtime_relocalises_on_the_others(
    frames: list[tuple[float, np.ndarray]],
    makers: dict[str, Callable[[], Backend]],
    tmp_path: Path,
) -> None:
    path = tmp_path / "room.kvmap"
    with Tracker(TrackerConfig.from_dict(CONFIG), makers["torch"]()) as tracker:
        for stamp, image in frames[:12]:
            tracker.push_frame(image, timestamp=stamp)
        tracker.save_map(path)
        tracker.backend.close()
    sessions = {}
    for name, make in makers.items():  # the next session, on each runtime
        backend = make()
        with Tracker.from_map(path, backend) as tracker:
            sessions[name] = [tracker.push_frame(image, timestamp=t) for t, image in frames[12:]]
        backend.close()
    for name in ("onnx", "openvino"):
        assert sessions[name][0].state is TrackingState.RELOCALIZING  # relocalises first
        assert_same_poses(sessions[name], sessions["torch"])

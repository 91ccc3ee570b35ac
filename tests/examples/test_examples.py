"""Every example runs: offline with the simulated backend, and with the small golden Pi3 weights on
real TUM frames (``--weights``)."""

from __future__ import annotations

import importlib.util
import shutil
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType

import cv2
import numpy as np
import pytest

from tests.conftest import OnnxExport
from tests.helpers import PROJECT_ROOT, shared_path

EXAMPLES = PROJECT_ROOT / "examples"


def load(name: str) -> ModuleType:
    """Import ``examples/<name>.py`` as a module (examples are scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def one_torch_thread() -> Iterator[None]:
    """The golden model is tiny: one thread is as fast and does not fight other jobs for cores."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def real() -> list[str]:
    weights = shared_path("golden", "pi3", "weights.safetensors")
    return ["--weights", str(weights), "--source", str(shared_path("data", "tum_fr2_desk"))]


def test_every_example_is_a_script_with_a_main() -> None:
    names = sorted(p.stem for p in EXAMPLES.glob("*.py"))
    assert names == [
        "camera_loop", "object_from_one_box", "object_masks", "object_scan_and_relocalise",
        "ray_streams", "swap_backends",
    ]
    for name in names:
        text = (EXAMPLES / f"{name}.py").read_text()
        assert 'if __name__ == "__main__":\n    main()' in text and text.startswith('"""')


def test_camera_loop(capsys: pytest.CaptureFixture[str]) -> None:
    app = load("camera_loop").main(["--frames", "90"])
    # frames 60-89 are "covered": no valid pose (the first two are low-confidence TRACKING frames,
    # then lost_after = 3 moves to RELOCALIZING), and no recovery before the end
    assert app.frames_drawn == 60 and app.hints_shown == 30
    assert "frame 62: TRACKING -> RELOCALIZING (LOW_CONFIDENCE)" in app.log
    assert "frame 30: keyframe 1 added" in app.log
    assert "drew 60 frames" in capsys.readouterr().out


def test_object_scan_and_relocalise(tmp_path: Path) -> None:
    outcome = load("object_scan_and_relocalise").main(
        ["--scan-frames", "60", "--relocalise-frames", "10", "--map", str(tmp_path / "o.kvmap")]
    )
    assert outcome.keyframes_saved >= 5  # a keyframe per ~10 degrees over 60 degrees
    assert outcome.frames_to_relocalise == 2  # valid from the 3rd frame (recover_after = 3)
    # session-2 poses land in session 1's world frame: the 3 mm simulated noise, not a jump
    assert outcome.relocalised_error_m < 0.01
    assert (tmp_path / "o.kvmap").is_file()


def test_swap_backends() -> None:
    outcome = load("swap_backends").main(["--frames", "40"])
    assert outcome.mismatch_refused and outcome.all_poses_valid_after_swap
    assert outcome.backends_used[:20] == ["1:simulated/float64"] * 20
    assert outcome.backends_used[20:] == ["2:simulated/float64"] * 20


def test_swap_backends_on_a_source_shorter_than_frames_still_swaps(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    example = load("swap_backends")
    twenty = example.simulated
    monkeypatch.setattr(example, "simulated", lambda frames: twenty(20))  # 20 frames, not 120
    outcome = example.main(["--frames", "120"])
    assert outcome.swapped_at == 10 and outcome.all_poses_valid_after_swap
    assert outcome.backends_used == ["1:simulated/float64"] * 10 + ["2:simulated/float64"] * 10
    assert "10 of 10 poses after the swap valid" in capsys.readouterr().out


@pytest.mark.parametrize("use_box", [False, True])
def test_object_masks(use_box: bool) -> None:
    outcome = load("object_masks").main(["--frames", "40"] + (["--box"] if use_box else []))
    assert outcome.frames == outcome.valid_poses == 40
    # one degree per frame and a keyframe per 10 degrees of view change (a box adds background,
    # which moves the estimated object centre and slows the rule down)
    assert 3 <= len(outcome.keyframe_frames) <= 5 and outcome.keyframe_frames[0] == 0


@pytest.mark.parametrize("segmenter", [False, True])
def test_object_from_one_box(segmenter: bool) -> None:
    outcome = load("object_from_one_box").main(
        ["--frames", "60"] + (["--segmenter"] if segmenter else []))
    assert outcome.frames == 60 and outcome.sources["given"] == 1
    assert outcome.sources["segmented" if segmenter else "predicted"] == 59
    assert min(outcome.tracked_ious) >= 0.8 and outcome.anchor_in_view


@pytest.fixture
def pi3_export_in_cache(onnx_exports: Callable[[str], OnnxExport]) -> Path:
    """The session's golden Pi3 export, placed where ``export_onnx.onnx_backend(weights)`` looks
    for an export of those weights (the session's ``KVTRACKER_CACHE_DIR``): the example then
    reuses it instead of exporting the checkpoint again (30-60 s of CPU)."""
    from kvtracker_sdk.backends.onnx_manifest import read_manifest
    from kvtracker_sdk.export_onnx.reuse import default_cache_dir

    folder = onnx_exports("pi3").folder
    slot = default_cache_dir() / f"pi3-{read_manifest(folder).weights_fingerprint}"
    if not slot.exists():
        shutil.copytree(folder, slot)
    return slot / "manifest.json"


@pytest.mark.slow
@pytest.mark.usefixtures("one_torch_thread")
def test_examples_with_real_weights(
    real: list[str], tmp_path: Path, pi3_export_in_cache: Path
) -> None:
    app = load("camera_loop").main(["--frames", "4", *real])
    assert app.frames_drawn == 4
    stamp = pi3_export_in_cache.stat().st_mtime_ns
    swapped = load("swap_backends").main(["--frames", "4", *real])
    assert swapped.mismatch_refused and swapped.backends_used[-1] == "2:onnx/float32"
    assert pi3_export_in_cache.stat().st_mtime_ns == stamp  # the session's export, not a new one
    scanned = load("object_scan_and_relocalise").main(
        ["--scan-frames", "3", "--relocalise-frames", "4", "--bbox", "100,80,540,400", *real]
    )
    assert scanned.keyframes_saved >= 1 and scanned.relocalised_error_m is None  # no ground truth
    masks = tmp_path / "masks"
    masks.mkdir()
    for k in range(3):
        mask = np.zeros((480, 640), np.uint8)
        mask[100:380, 150:500] = 255
        cv2.imwrite(str(masks / f"{k}.png"), mask)
    masked = load("object_masks").main(["--frames", "3", *real, "--masks", str(masks)])
    assert masked.frames == 3
    one_box = load("object_from_one_box").main(["--frames", "3", *real, "--box", "200,150,440,330"])
    assert one_box.frames == 3 and one_box.sources["given"] == 1

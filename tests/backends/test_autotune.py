"""The tuner (``backends/autotune.py``) on stand-in backends with known speeds and deviations,
and its choice kept per machine and model (``io/files/tune_cache.py``).

Stand-ins: each sleeps a fixed time per step (a factor of 2 or more apart, so that the median of
a few steps orders them even on a busy CPU) and returns the reference pose plus a fixed offset
(its deviation from fp32).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from kvtracker_sdk.backends.autotune import (
    Candidate,
    TuneProblem,
    default_candidates,
    synthetic_frames,
    tune,
)
from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.io.files import tune_cache

SIZE = (28, 28)
# candidate -> (seconds per step, pose offset from the fp32 reference)
PROFILE = {
    ("torch", "float32"): (0.024, 0.0),
    ("torch", "bfloat16"): (0.012, 3e-3),
    ("openvino", "float32"): (0.006, 1e-6),
    ("openvino", "bfloat16"): (0.002, 1.4e-2),  # fastest, but 4.7x torch bf16's deviation
}


class _Cache:
    def __init__(self, dtype: str) -> None:
        self.dtype = dtype

    def to(self, *, dtype: Any) -> _Cache:
        return _Cache(str(dtype).removeprefix("torch."))


class _StandIn:
    """A backend whose step takes ``seconds`` and whose pose is off by ``offset``."""

    def __init__(self, candidate: Candidate, closed: list[str]) -> None:
        self.seconds, self.offset = PROFILE[(candidate.runtime, candidate.dtype)]
        self.info = SimpleNamespace(family="pi3", patch_size=14, dtype=candidate.dtype,
                                    weights_fingerprint="w")  # fmt: skip
        self.name, self.closed = candidate.name, closed

    def map(self, images: np.ndarray) -> Any:
        return SimpleNamespace(cache=_Cache(self.info.dtype))

    def track(self, image: np.ndarray, cache: Any, *, heads: Any) -> Any:
        time.sleep(self.seconds)
        pose = np.eye(4)
        pose[0, 3] = float(image.mean()) / 255.0 + self.offset  # depends on the frame
        return SimpleNamespace(pose=pose)

    def close(self) -> None:
        self.closed.append(self.name)


def _opener(closed: list[str], broken: set[str] = frozenset()) -> Any:  # type: ignore[assignment]
    def open_candidate(candidate: Candidate) -> Any:
        if candidate.runtime in broken:
            raise RuntimeError(f"{candidate.runtime} is not installed")
        return _StandIn(candidate, closed)

    return open_candidate


CANDIDATES = [Candidate(r, d, 1) for r, d in PROFILE]


@pytest.mark.parametrize("interleave", [True, False])
def test_the_fastest_within_torch_bf16s_deviation_is_chosen(interleave: bool) -> None:
    closed: list[str] = []
    result = tune(_opener(closed), CANDIDATES, TuneProblem(2, size=SIZE), seconds=0.3,
                  interleave=interleave)  # fmt: skip
    assert result.chosen == Candidate("openvino", "float32", 1), result.table()
    assert result.deviation_bound == pytest.approx(3e-3)
    rows = {row.candidate.runtime + row.candidate.dtype: row for row in result.results}
    too_imprecise = rows["openvinobfloat16"]
    assert not too_imprecise.eligible and "deviation" in too_imprecise.note
    assert too_imprecise.median_s is not None and too_imprecise.median_s < rows[
        "openvinofloat32"].median_s  # fmt: skip
    assert all(row.steps >= 3 for row in result.results)
    assert "openvino-fp32-t1" in result.reason and "openvino-bf16-t1" in result.reason
    assert sorted(closed) == sorted(c.name for c in CANDIDATES)  # every backend closed
    assert "| openvino-fp32-t1 |" in result.table() and "chosen" in result.table()


def test_a_missing_runtime_is_reported_and_the_rest_still_chosen() -> None:
    result = tune(_opener([], broken={"openvino"}), CANDIDATES, TuneProblem(2, size=SIZE),
                  seconds=0.1)  # fmt: skip
    assert result.chosen == Candidate("torch", "bfloat16", 1)
    notes = [row.note for row in result.results if row.candidate.runtime == "openvino"]
    assert all(note.startswith("unavailable: RuntimeError") for note in notes)


def test_candidates_and_problems_are_checked() -> None:
    with pytest.raises(ConfigError):
        tune(_opener([]), [Candidate("openvino", "float32", 1)], TuneProblem(2, size=SIZE))
    with pytest.raises(ConfigError):
        Candidate("tensorrt", "float32", 1)
    with pytest.raises(ConfigError):
        Candidate("torch", "float32", 0)
    with pytest.raises(ConfigError):
        TuneProblem(0)
    names = [c.name for c in default_candidates(["torch", "onnx"], cores=4)]
    assert names == ["torch-fp32-t1", "torch-fp32-t2", "torch-fp32-t4", "torch-bf16-t1",
                     "torch-bf16-t2", "torch-bf16-t4", "onnx-fp32-tauto"]  # fmt: skip
    frames = synthetic_frames(3, 28, 42, seed=1)
    assert frames.shape == (3, 28, 42, 3) and frames.dtype == np.uint8
    assert np.array_equal(frames, synthetic_frames(3, 28, 42, seed=1))


def test_the_choice_is_kept_per_machine_and_read_back_validated(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.delenv("KVTRACKER_CACHE_DIR", raising=False)
    assert tune_cache.tune_cache_dir() == tmp_path / "xdg" / "kvtracker_sdk" / "tune"
    result = tune(_opener([]), CANDIDATES, TuneProblem(2, size=SIZE), seconds=0.1)
    key = tune_cache.choice_key("da3-small", TuneProblem(2, size=SIZE))
    path = tune_cache.remember_choice(key, result)
    assert path.parent == tune_cache.tune_cache_dir()
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary left
    kept = tune_cache.cached_choice(key)
    assert kept is not None and kept[0] == result.chosen and kept[1] == result.reason
    # another machine (core count), other weights or another map size: not this choice
    assert tune_cache.cached_choice({**key, "cores": key["cores"] + 1}) is None
    assert tune_cache.cached_choice(tune_cache.choice_key("da3-base", TuneProblem(2, size=SIZE)))\
        is None  # fmt: skip
    record = json.loads(path.read_text())
    for bad in ({**record, "schema": 99}, {**record, "key": {**key, "cpu": "other"}},
                {**record, "chosen": {**record["chosen"], "threads": 10_000}},
                {**record, "chosen": {**record["chosen"], "runtime": "tensorrt"}}):  # fmt: skip
        path.write_text(json.dumps(bad))
        assert tune_cache.cached_choice(key) is None
    path.write_text("{not json")
    assert tune_cache.cached_choice(key) is None

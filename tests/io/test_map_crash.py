"""Crash safety of ``save_map``: killing the writer, or failing mid-write, never loses the old map.

Child processes save a large map (~76 MB) over an existing small one and are SIGKILLed: after the
new file is complete but before ``os.replace`` (made deterministic by stalling the child's fsync),
and at seeded random moments after the temporary file appears (the child is first frozen with
SIGSTOP so the parent can see exactly how far it got). Whatever the moment, the target path must
hold the old map or the complete new one, both loading with verified checksums, and any leftover
temporary file must be hidden and not named like a map.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import BinaryIO

import numpy as np
import pytest

from kvtracker_sdk.cache import KeyframeMap
from kvtracker_sdk.errors import MapError, MapIOError
from kvtracker_sdk.io.map_file import map_file
from kvtracker_sdk.io.map_file.map_file import load_map, read_map_info, save_map
from tests.helpers import PROJECT_ROOT
from tests.io.map_factory import TRACKER_CONFIG, backend_info, make_map, maps_equal

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs POSIX signals"),
]

BIG = {
    "num_keyframes": 8,
    "layers": 8,
    "heads": 8,
    "head_dim": 64,
    "size": (224, 224),
    "generation": 99,
}

_CHILD = """
import json, os, sys, time
from kvtracker_sdk.io.map_file.map_file import save_map
from tests.io.map_factory import TRACKER_CONFIG, backend_info, make_map
target, stall, spec = sys.argv[1], sys.argv[2] == "stall", json.loads(sys.argv[3])
big = make_map(**{**spec, "size": tuple(spec["size"])})
if stall:  # the temporary file's fsync is the last step before os.replace
    real_fsync = os.fsync
    def stalled_fsync(fd):
        real_fsync(fd)
        print("fsynced", flush=True)
        time.sleep(600)  # not synchronisation: holds the child here until the parent kills it
    os.fsync = stalled_fsync
print("saving", flush=True)
save_map(target, big, tracker_config_json=TRACKER_CONFIG, mode="object",
         backend_info=backend_info(layers=spec["layers"], heads=spec["heads"], head_dim=spec["head_dim"]))
"""


def save_old(folder: Path) -> tuple[Path, KeyframeMap]:
    old = make_map()
    target = folder / "scene.kvmap"
    save_map(
        target, old, backend_info=backend_info(), tracker_config_json=TRACKER_CONFIG, mode="object"
    )
    return target, old


def start_child(target: Path, *, stall: bool) -> subprocess.Popen[str]:
    child = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(target), "stall" if stall else "run", json.dumps(BIG)],
        cwd=PROJECT_ROOT, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert child.stdout is not None and child.stdout.readline().strip() == "saving"
    return child


def temporaries(folder: Path) -> list[Path]:
    return [p for p in folder.iterdir() if p.name != "scene.kvmap"]


def _writing(folder: Path) -> bool:
    """A temporary file exists and has bytes in it (the file may be removed meanwhile)."""
    for tmp in temporaries(folder):
        try:
            if tmp.stat().st_size > 0:
                return True
        except FileNotFoundError:
            continue
    return False


def assert_no_stray_map(folder: Path) -> None:
    """Only the target is named like a map; the save's temporary file is hidden."""
    assert [p.name for p in folder.glob("*.kvmap")] == ["scene.kvmap"]
    for tmp in temporaries(folder):
        assert tmp.name.startswith(".") and not tmp.name.endswith(".kvmap"), tmp.name


def stage_of(folder: Path, target: Path) -> str:
    """How far a frozen child got: replaced, mid-write (a partial map on disk), or neither.

    A temporary file can have its full size before all its bytes are written (the writer may
    size it first), so only loading it with checksums tells complete from partial."""
    if read_map_info(target).generation == BIG["generation"]:
        return "replaced"
    for tmp in temporaries(folder):
        if tmp.stat().st_size > 0:
            try:
                load_map(tmp)
            except MapError:
                return "mid-write"
            return "written, not replaced"
    return "not started"


def kill(child: subprocess.Popen[str]) -> None:
    child.kill()  # SIGKILL: no cleanup handler runs
    child.wait(timeout=30)


def test_kill_after_write_before_replace_keeps_the_old_map(tmp_path: Path) -> None:
    target, old = save_old(tmp_path)
    child = start_child(target, stall=True)
    assert child.stdout is not None and child.stdout.readline().strip() == "fsynced"
    kill(child)
    assert maps_equal(load_map(target).keyframe_map, old)  # checksums verified by default
    assert_no_stray_map(tmp_path)
    (leftover,) = temporaries(tmp_path)  # the complete new map, under a name no one loads
    assert read_map_info(leftover).generation == BIG["generation"]


def test_kill_at_random_moments_leaves_old_or_new_map(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    stages = []
    new = make_map(**BIG)  # type: ignore[arg-type]
    # The first runs stop the child within 5 ms of its first bytes reaching the temporary file
    # (mid-write, as the 76 MB write takes longer), until one lands mid-write: on a loaded machine
    # the parent may be descheduled past the write, which is still a valid stage, only not the one
    # wanted here. (Waiting for bytes, not for the file: on a busy machine the child can sit
    # between creating the file and writing to it for longer than the window.) The last run stops
    # anywhere in the next half second (any stage; the assertions cover each).
    windows = [0.005] * 5 + [0.5]
    for run, window in enumerate(windows):
        if window < 0.5 and "mid-write" in stages:
            continue
        folder = tmp_path / f"run{run}"
        folder.mkdir()
        target, old = save_old(folder)
        child = start_child(target, stall=False)
        deadline = time.monotonic() + 60
        # Not synchronisation: polling for the child's temporary file (no event to wait on in
        # another process), then a random delay — the kill moments are what this test samples.
        while not _writing(folder) and child.poll() is None and time.monotonic() < deadline:
            time.sleep(0.0002)
        time.sleep(float(rng.uniform(0.0, window)))
        os.kill(child.pid, signal.SIGSTOP)  # freeze it, then look at exactly how far it got
        stage = stage_of(folder, target)
        kill(child)
        stages.append(stage)
        loaded = load_map(target).keyframe_map
        assert maps_equal(loaded, new if stage == "replaced" else old), stage
        assert_no_stray_map(folder)
    assert "mid-write" in stages, stages


@pytest.mark.parametrize(
    "failure", [OSError(errno.ENOSPC, "No space left on device"), KeyboardInterrupt()]
)
def test_a_failing_write_keeps_the_old_map_and_removes_the_temporary(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failure: BaseException
) -> None:
    target, old = save_old(tmp_path)

    def half_write(handle: BinaryIO, tensors: object, metadata: object, **_: object) -> int:
        handle.write(target.read_bytes()[:1000])
        raise failure

    monkeypatch.setattr(map_file, "write_safetensors", half_write)
    expected = MapIOError if isinstance(failure, OSError) else KeyboardInterrupt
    with pytest.raises(expected):
        save_map(
            target,
            make_map(seed=1),
            backend_info=backend_info(),
            tracker_config_json="{}",
            mode="scene",
        )
    assert maps_equal(load_map(target).keyframe_map, old)
    assert temporaries(tmp_path) == []

"""Camera files as a careless or hostile user writes them (seeded, in-process, ~1 s).

Every file holds something absurd, and gives a typed SDK error naming the offending field: never a raw ``ValueError``/``TypeError``/``RecursionError``/
``MemoryError``, never a hang (a FIFO), never a 300 MB message (a YAML alias bomb).
``benchmarks/fuzz_inputs.py`` runs more, each in a fresh process under a 3 GB address-space
limit.
"""

from __future__ import annotations

import json
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from kvtracker_sdk.errors import KVTrackerError, SourceError
from kvtracker_sdk.geometry.camera import Camera
from kvtracker_sdk.io.sources.camera_files import read_camera_file
from tests.hostile_inputs import camera_cases

DEFAULT_CASES = 300
GOOD = {"fx": 520.9, "fy": 521.0, "cx": 325.1, "cy": 249.7, "width": 640, "height": 480}


@pytest.fixture(autouse=True)
def no_hang() -> Iterator[None]:
    """Fail instead of hanging (a FIFO read used to block forever)."""
    def fail(*_: object) -> None:
        raise TimeoutError("reading a camera file hung")

    previous = signal.signal(signal.SIGALRM, fail)
    signal.alarm(60)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, previous)


def plausible(camera: Camera) -> bool:
    from kvtracker_sdk.io.sources.camera_files import FOCAL_PER_SIDE, MAX_DISTORTION, MAX_IMAGE_SIDE

    side = max(camera.width, camera.height)
    low, high = FOCAL_PER_SIDE[0] * side, FOCAL_PER_SIDE[1] * side
    return (1 <= camera.width <= MAX_IMAGE_SIDE and 1 <= camera.height <= MAX_IMAGE_SIDE
            and low <= camera.fx <= high and low <= camera.fy <= high
            and -camera.width <= camera.cx <= 2 * camera.width
            and -camera.height <= camera.cy <= 2 * camera.height
            and all(abs(d) <= MAX_DISTORTION for d in camera.distortion))


def test_seeded_hostile_camera_files_give_a_typed_error_naming_the_field(
    tmp_path: Path,
) -> None:
    pytest.importorskip("yaml")
    unnamed, untyped, accepted, slow = [], [], [], []
    for case in camera_cases(DEFAULT_CASES, seed=34):
        path = case.make(tmp_path)
        start = time.perf_counter()
        try:
            camera = read_camera_file(path)
            accepted.append((case.name, plausible(camera)))
        except KVTrackerError as exc:
            if not any(field in str(exc) for field in case.fields):
                unnamed.append((case.name, str(exc)[:200]))
            if len(str(exc)) > 2000:
                unnamed.append((case.name, f"a {len(str(exc))}-character message"))
        except Exception as exc:  # noqa: BLE001 - counting what escapes
            untyped.append((case.name, type(exc).__name__))
        if time.perf_counter() - start > 5:
            slow.append(case.name)
    assert (untyped, unnamed, accepted, slow) == ([], [], [], [])


def test_a_plausible_camera_file_still_loads(tmp_path: Path) -> None:
    path = tmp_path / "camera.json"
    path.write_text(json.dumps({**GOOD, "distortion": [0.23, -0.78, -0.003, -0.0001, 0.92]}))
    camera = read_camera_file(path)
    assert plausible(camera) and camera.width == 640 and camera.distortion[4] == 0.92


@pytest.mark.parametrize(
    ("field", "value"),
    [("width", float("nan")), ("width", float("inf")), ("width", "640"), ("width", [640]),
     ("width", 1e300), ("width", 10**30), ("fx", 5e-324), ("fx", 1e308)],
)
def test_each_absurd_value_reported_is_refused_naming_its_field(
    tmp_path: Path, field: str, value: object
) -> None:
    path = tmp_path / "camera.json"
    path.write_text(json.dumps({**GOOD, field: value}))
    with pytest.raises(SourceError, match=field):
        read_camera_file(path)


def test_huge_distortion_coefficients_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "camera.json"
    path.write_text(json.dumps({**GOOD, "distortion": [1e308, 0, 0, 0, 0]}))
    with pytest.raises(SourceError, match=r"distortion\[0\]"):
        read_camera_file(path)


def test_deep_nesting_a_fifo_and_dev_zero_are_refused_at_once(tmp_path: Path) -> None:
    import os

    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(SourceError, match="nested"):
        read_camera_file(deep)
    fifo = tmp_path / "fifo.json"
    os.mkfifo(fifo)
    with pytest.raises(SourceError, match="FIFO"):
        read_camera_file(fifo)
    zero = tmp_path / "zero.json"
    zero.symlink_to("/dev/zero")
    with pytest.raises(SourceError, match="character device"):
        read_camera_file(zero)


def test_a_yaml_alias_bomb_is_refused_quickly_with_a_short_message(tmp_path: Path) -> None:
    pytest.importorskip("yaml")
    lines = ["a: &a [x, x, x, x, x, x, x, x, x]"]
    for i in range(9):
        previous, name = chr(97 + i), chr(98 + i)
        lines.append(f"{name}: &{name} [" + ", ".join([f"*{previous}"] * 9) + "]")
    path = tmp_path / "bomb.yaml"
    path.write_text("\n".join(lines) + "\n")
    assert path.stat().st_size < 1024
    start = time.perf_counter()
    with pytest.raises(SourceError, match="alias") as caught:
        read_camera_file(path)
    assert time.perf_counter() - start < 2.0 and len(str(caught.value)) < 1000

"""``kvtracker track FRAMES --load-map obj.kvmap --out run/``: an object map made yesterday finds
its object today with no box; the mode comes from the map. The frames are the simulated desk's
second walk (``benchmarks/object_desk.py``: it pans onto the object, in view from frame ~29),
written as PNG files; the simulated backend stands in for the weights."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import pytest

from benchmarks.object_desk import SIZE, Layout, first_walk, layout
from kvtracker_sdk.geometry.boxes import box_iou
from tests.cli.invoke import invoke

FIRST, SECOND = 60, 45


@pytest.fixture(scope="module")
def desk() -> Layout:
    return layout("desk", FIRST)


@pytest.fixture(scope="module")
def object_map(desk: Layout, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("maps") / "obj.kvmap"
    first_walk(desk, path)
    return path


@pytest.fixture(scope="module")
def frames(desk: Layout, tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("frames")
    for frame in desk.backend().frames(SIZE, textured=False, start=FIRST, stop=FIRST + SECOND):
        cv2.imwrite(str(folder / f"{frame.index:05d}.png"), frame.image[..., ::-1])  # RGB->BGR
    return folder


@pytest.fixture
def simulated(desk: Layout, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("kvtracker_sdk.cli.track.open_backend", lambda *a, **k: desk.backend())


@pytest.mark.usefixtures("simulated")
def test_track_finds_the_object_of_a_loaded_map_without_a_box(
    desk: Layout, object_map: Path, frames: Path, tmp_path: Path
) -> None:
    result = invoke("track", frames, "--load-map", object_map, "--out", tmp_path / "run")
    assert result.exit_code == 0, result.output
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["config"]["mode"] == "object"  # from the map
    document = json.loads((tmp_path / "run" / "object.json").read_text())
    records = document["frames"]
    assert len(records) == SECOND and records[0]["source"] is None  # searching: no region
    found = next(i for i, r in enumerate(records) if r["source"] == "predicted")
    in_view = next(i for i in range(SECOND) if (b := desk.scene.object_box(
        desk.truth.poses[FIRST + i], SIZE)) and b[0] > 0 and b[2] < SIZE[1])
    assert in_view <= found <= in_view + 10
    for record in records[found:]:
        truth = desk.scene.object_box(desk.truth.poses[FIRST + record["frame_index"]], SIZE)
        assert record["source"] == "predicted" and box_iou(tuple(record["box"]), truth) >= 0.8
    assert document["object_frame"]["up"] is not None


@pytest.mark.usefixtures("simulated")
def test_an_object_never_found_tells_what_to_pass(
    object_map: Path, frames: Path, tmp_path: Path
) -> None:
    config = tmp_path / "config.json"
    config.write_text(json.dumps({"mode": "object", "resolution": 224,
                                  "object": {"search_frames": 5}}))
    looking_away = tmp_path / "away"
    looking_away.mkdir()
    for path in sorted(frames.iterdir())[:15]:  # the camera has not turned to the object yet
        (looking_away / path.name).write_bytes(path.read_bytes())
    result = invoke("track", looking_away, "--load-map", object_map, "--config", config,
                    "--out", tmp_path / "run")
    assert result.exit_code == 3, result.output  # unusable input: the object is not there
    assert "not found" in result.output and "--bbox x0,y0,x1,y1 --bbox-once" in result.output
    assert (tmp_path / "run" / "object.json").is_file()  # the outputs are written first

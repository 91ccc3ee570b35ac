"""Object mode from one box where objects really are: on a desk, beside another, against a wall,
and found again in a new process from the saved map.

Scenes (``SimulatedScene.desk``, simulated backend, frames 196x252, Pi3's d = 224):

* ``desk``: a 12 x 9 x 16 cm cuboid on a table plane, a 10 x 10 x 13 cm cuboid 10+ cm beside it;
  a 720-frame hand-held walk around it (``desk_orbit``: 0.5 m +-10 %, looking down 13-39 deg);
* ``wall``: the same against a wall plane 2 cm behind it (two planes), the walk going to and fro
  over the 140 degrees in front of the wall;
* ``floating``: the sphere with nothing around it (``tests/tracking/test_object_region.py``'s
  run), to show its figures did not move.

Each run: the true silhouette box on frame 0 only, 1.5 s of "camera covered" (frames 400-445),
pose noise 3 mm / 0.1 deg; on the desk and the wall the backend is confident only while the
tracked image shows the whole object (``object_in_view``: a network cannot place a camera
against an object's map without seeing the object); the floating run is the test's, unchanged. Measured: predicted box IoU against the true silhouette box on the
tracked frames (pose valid); the fused object points' distance to the true surface (the map
aligned to the truth by a Sim(3) fit of the keyframes' camera centres); the object frame's
origin against the true centre (share of the bounding radius); the oriented extent per axis
against the true size (each true axis matched to the box axis closest to it).

Reload (``desk`` and ``wall``): the map saved after the run is loaded by a *new process*
(``python -m benchmarks.object_desk --reload``), which tracks a second walk of the same scene
("the next day": another seed) that starts looking 60 degrees away and pans onto the object over
1.5 s, with no box at all: frames until the region is predicted with IoU >= 0.8 after the object
came into view (its whole silhouette in the image), and the IoU after that.

    python -m benchmarks.object_desk [--layouts desk wall floating] [--out ...]

Prints a markdown table and writes ``benchmarks/results/object_desk.json`` (date, machine, load,
command). Accuracy, not timing: the numbers do not depend on the machine.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import GroundTruth, SimulatedScene
from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.cli.demo_trajectory import desk_orbit, handheld_orbit
from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.geometry.boxes import box_iou
from kvtracker_sdk.geometry.sim3 import umeyama_alignment
from kvtracker_sdk.tracking.facade.tracker import Tracker
from kvtracker_sdk.tracking.object.object_model import fused_object_points, sampling_step
from kvtracker_sdk.types import FrameResult, ObjectFrame, RegionSource

RESULTS = Path(__file__).parent / "results"
SIZE = (196, 252)
LOSS = (400, 445)
IOU = 0.8
SURFACE_M = 0.01
DAY2_FRAMES = 300
PAN_FRAMES = 45  # the second walk starts 60 degrees away and pans onto the object in 1.5 s
PAN_DEG = 60.0


@dataclass(frozen=True)
class Layout:
    name: str
    truth: GroundTruth  # the first walk's frames, then the second's (reload)
    scene: SimulatedScene
    first_frames: int

    def backend(self) -> SimulatedBackend:
        return SimulatedBackend(self.truth, scene=self.scene, seed=2, translation_noise_m=0.003,
                                rotation_noise_deg=0.1, loss_segments=[LOSS],
                                object_in_view=self.name != "floating")


def _panned_in(walk: GroundTruth) -> np.ndarray:
    """``walk``'s poses, the first ``PAN_FRAMES`` turned away about world z (up) by up to
    ``PAN_DEG``: the camera pans onto the object."""
    poses = walk.poses.copy()
    for i in range(PAN_FRAMES):
        turn = Rotation.from_euler("z", PAN_DEG * (1.0 - i / PAN_FRAMES), degrees=True)
        poses[i, :3, :3] = turn.as_matrix() @ poses[i, :3, :3]
    return poses


def layout(name: str, frames: int = 720) -> Layout:
    """The scene and the two walks of ``name`` (desk, wall or floating)."""
    if name == "floating":
        first = handheld_orbit(frames, seed=3)
        return Layout(name, first, SimulatedScene.around(first.poses), frames)
    wall = name == "wall"
    first = desk_orbit(frames, seed=3, wall=wall)
    second = desk_orbit(DAY2_FRAMES, seed=11, wall=wall)
    poses = np.concatenate([first.poses, _panned_in(second)])
    truth = GroundTruth(np.arange(len(poses)) / 30.0, poses)
    # the scene where the full walk looks (a shorter one is the same scene, walked faster)
    scene = SimulatedScene.desk(desk_orbit(720, seed=3, wall=wall).poses, wall=wall)
    return Layout(name, truth, scene, frames)


def _alignment(kf_map: KeyframeMap, truth: GroundTruth) -> Any:
    """The Sim(3) taking the map's world to the true one: a fit of the keyframes' camera centres
    and of points 0.3 m along their x and z axes (centres alone leave the rotation about an arc
    of views poorly fixed)."""
    estimate = np.array([kf.T_world_cam for kf in kf_map.keyframes])
    true = np.array([truth.poses[kf.frame_index] for kf in kf_map.keyframes])
    scale = umeyama_alignment(estimate[:, :3, 3], true[:, :3, 3]).scale
    def spread(poses: np.ndarray, length: float) -> np.ndarray:
        return np.concatenate([poses[:, :3, 3], poses[:, :3, 3] + length * poses[:, :3, 0],
                               poses[:, :3, 3] + length * poses[:, :3, 2]])
    return umeyama_alignment(spread(estimate, 0.3 / scale), spread(true, 0.3))


def object_figures(kf_map: KeyframeMap, frame: ObjectFrame, scene: SimulatedScene,
                   truth: GroundTruth) -> dict[str, Any]:
    """Surface, origin and extent figures of the map's object against the scene's truth."""
    sim3 = _alignment(kf_map, truth)
    fused = fused_object_points(kf_map.keyframes, step=sampling_step(kf_map.keyframes))
    distance = scene.object_surface_distance(sim3.apply_to_points(fused))
    origin = sim3.apply_to_points(frame.T_world_object[:3, 3][None])[0]
    T_world_box = frame.T_world_object @ frame.extent.T_ref_box
    box_axes = sim3.rotation @ T_world_box[:3, :3]
    sizes = frame.extent.size * sim3.scale
    if scene.object_shape is not None:
        true_axes, true_sizes = scene.object_shape.rotation, scene.object_shape.size
    else:
        true_axes, true_sizes = np.eye(3), np.full(3, 2.0 * scene.object_radius)
    errors = []
    for axis in range(3):
        match = int(np.argmax(np.abs(true_axes[:, axis] @ box_axes)))
        errors.append(float(abs(sizes[match] - true_sizes[axis]) / true_sizes[axis]))
    return {
        "fused_points": int(len(fused)),
        "within_1cm": float(np.mean(distance <= SURFACE_M)),
        "surface_distance_p50_mm": float(1e3 * np.median(distance)),
        "origin_error_of_radius": float(
            np.linalg.norm(origin - scene.object_centre) / scene.object_radius),
        "extent_error_per_axis": errors,
        "has_up": frame.up is not None,
        "up_error_deg": None if frame.up is None else float(np.degrees(np.arccos(np.clip(
            (sim3.rotation @ frame.up)[2], -1.0, 1.0)))),
    }


def _true_boxes(scene: SimulatedScene, truth: GroundTruth, indices: range) -> list[Any]:
    return [scene.object_box(truth.poses[i], SIZE) for i in indices]


def iou_figures(results: list[FrameResult], boxes: list[Any]) -> dict[str, Any]:
    """IoU of the predicted box with the true silhouette box over the tracked frames."""
    ious = [box_iou(r.region.box, b) if b is not None and r.region is not None else 0.0
            for r, b in zip(results, boxes, strict=True) if r.pose_valid]
    values = np.array(ious) if ious else np.zeros(1)
    return {"tracked": len(ious), "frames": len(results),
            "iou_ok": float(np.mean(values >= IOU)), "iou_min": float(values.min()),
            "iou_p5": float(np.quantile(values, 0.05)), "iou_median": float(np.median(values))}


def first_walk(lay: Layout, map_path: Path | None = None) -> dict[str, Any]:
    """Track the first walk from its frame-0 box; save the map to ``map_path`` if given."""
    backend = lay.backend()
    indices = range(lay.first_frames)
    boxes = _true_boxes(lay.scene, lay.truth, indices)
    results = []
    with Tracker(TrackerConfig(resolution=224, mode="object"), backend) as tracker:
        for frame in backend.frames(SIZE, textured=False, stop=lay.first_frames):
            bbox = boxes[0] if frame.index == 0 else None
            results.append(tracker.push_frame(frame.image, timestamp=frame.timestamp, bbox=bbox))
        kf_map, frame0 = tracker.keyframe_map, tracker.object.frame
        assert kf_map is not None and frame0 is not None
        if map_path is not None:
            tracker.save_map(map_path)
    out = iou_figures(results, boxes)
    out["keyframes"] = len(kf_map.keyframes)
    out["frame0_box_iou_ok"] = float(np.mean([b is not None and box_iou(boxes[0], b) >= IOU
                                              for b in boxes]))
    out.update(object_figures(kf_map, frame0, lay.scene, lay.truth))
    return out


def second_walk(lay: Layout, map_path: Path, *, frames: int | None = None) -> dict[str, Any]:
    """Load ``map_path`` (no box, mode from the map) and track the second walk (its first
    ``frames``, or all of it)."""
    backend = lay.backend()
    stop = len(lay.truth) if frames is None else lay.first_frames + frames
    indices = range(lay.first_frames, stop)
    boxes = _true_boxes(lay.scene, lay.truth, indices)
    results = []
    with Tracker.from_map(map_path, backend) as tracker:  # the mode comes from the map
        mode = tracker.config.mode.value
        for frame in backend.frames(SIZE, textured=False, start=lay.first_frames, stop=stop):
            results.append(tracker.push_frame(frame.image, timestamp=frame.timestamp))
    in_view = next(i for i, b in enumerate(boxes)
                   if b is not None and b[0] > 0 and b[1] > 0 and b[2] < SIZE[1] and b[3] < SIZE[0])
    found = next((i for i, (r, b) in enumerate(zip(results, boxes, strict=True))
                  if r.region is not None and r.region.source is RegionSource.PREDICTED
                  and b is not None and box_iou(r.region.box, b) >= IOU), None)
    after = range(found, len(results)) if found is not None else range(0)
    out = iou_figures([results[i] for i in after], [boxes[i] for i in after])
    out.update({"mode": mode, "in_view_frame": in_view,
                "found_frame": found,
                "frames_to_find": None if found is None else found - in_view,
                "sources_before": sorted({r.region.source.value for r in results[: found or 0]
                                          if r.region is not None})})
    return out


def reload_in_new_process(name: str, map_path: Path, *, frames: int | None = None) -> dict[str, Any]:
    """``second_walk`` (its first ``frames``, or all) in a fresh Python process (the map is all
    they share)."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    more = [] if frames is None else ["--reload-frames", str(frames)]
    done = subprocess.run(
        [sys.executable, "-m", "benchmarks.object_desk", "--reload", name, str(map_path), *more],
        capture_output=True, text=True, env=env, check=True, cwd=Path(__file__).parents[1])
    result: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def table(rows: dict[str, dict[str, Any]]) -> str:
    lines = ["| layout | tracked frames | box IoU >= 0.8 | IoU p5 / median | points within 1 cm "
             "| origin error (of radius) | extent error per axis | reload: frames to find "
             "| reload: IoU >= 0.8 |", "|---|---|---|---|---|---|---|---|---|"]
    for name, row in rows.items():
        first, second = row["first"], row.get("reload")
        errors = " / ".join(f"{100 * e:.0f} %" for e in first["extent_error_per_axis"])
        reload = ("–", "–") if second is None else (
            str(second["frames_to_find"]), f"{100 * second['iou_ok']:.0f} %")
        lines.append(
            f"| {name} | {first['tracked']}/{first['frames']} | {100 * first['iou_ok']:.1f} % | "
            f"{first['iou_p5']:.2f} / {first['iou_median']:.2f} | "
            f"{100 * first['within_1cm']:.0f} % | {100 * first['origin_error_of_radius']:.1f} % "
            f"| {errors} | {reload[0]} | {reload[1]} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--layouts", nargs="+", default=["desk", "wall", "floating"])
    parser.add_argument("--out", type=Path, default=RESULTS / "object_desk.json")
    parser.add_argument("--reload", nargs=2, metavar=("LAYOUT", "MAP"), help=argparse.SUPPRESS)
    parser.add_argument("--reload-frames", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.reload:  # the child process of reload_in_new_process
        result = second_walk(layout(args.reload[0]), Path(args.reload[1]),
                             frames=args.reload_frames)
        print(json.dumps(result))
        return result
    rows: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory() as folder:
        for name in args.layouts:
            lay = layout(name)
            map_path = None if name == "floating" else Path(folder) / f"{name}.kvmap"
            rows[name] = {"first": first_walk(lay, map_path)}
            if map_path is not None:
                rows[name]["reload"] = reload_in_new_process(name, map_path)
            print(name, json.dumps(rows[name]), file=sys.stderr)
    print(table(rows))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": platform.platform(), "load_average": os.getloadavg(),
        "command": "python -m benchmarks.object_desk " + " ".join(argv or sys.argv[1:]),
        "rows": rows}, indent=2) + "\n")
    return rows


if __name__ == "__main__":
    main()

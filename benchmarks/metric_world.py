"""An AR-ready world on a real trajectory: metric scale from depth frames or a known size, and
gravity up — simulated sensors over TUM fr2_desk's 100 s ground truth (2,981 frames at 30 Hz).

The simulated network (``SimulatedBackend``, seed 0) answers each mapping pass in a hidden frame
of random scale: its first map measures 0.20 world units per metre, so metres must come from the
sensors. Sensors (``backends/simulated_sensors.py``): depth rendered from the simulated scene with
1 % noise, 5 % of pixels missing and depth edges invalid; an accelerometer with 0.05 m/s² noise
per axis. The tracker runs with its defaults at resolution 224 (sim_session's setup).

Runs:

* ``mono``: RGB only. Its world scale (0.2 units per metre) and its Sim(3)-aligned ATE.
* ``rgbd``: depth on every frame, saved at ``reload_at`` and continued in a new tracker loaded
  from the file (``Tracker.from_map``). **Scale error** of a map = ``|world units per metre - 1|``,
  read exactly from the simulation (the gauge's scale times the pass's hidden scale) at every
  installed map: after the first map, at the end, and the largest over the run. **ATE (m)**: RMSE
  of the camera centres after a rigid (SE(3)) alignment — no scale fitted.
* ``rgbd_gravity``: the same with the accelerometer. **World up error**: per window of 100 tracked
  frames, the tilt of the world's z axis from the true up — the rotation between the estimated and
  true world frames is the chordal mean of ``R_est R_trueᵀ`` over the window (one frame's pose
  noise, 0.3° per axis, would otherwise be read as a tilt); the per-frame value is reported too.
  Also the ROS 2 bag of the run (``write_ros2_bag``) read back: the same tilt of the map frame's z.
* ``known_size``: object mode on a 720-frame orbit of the 0.6 m sphere, its true height stated on
  frame 0 (``tracker.world.set_object_height``); and a scene-mode run where the true distance
  between the camera centres of frames 0 and ``distance_frame`` is stated
  (``tracker.world.set_known_distance``).

    python -m benchmarks.metric_world [--frames 2981] [--out benchmarks/results/metric_world.json]

Prints a table and writes the JSON (date, machine, load, command, every number).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from kvtracker_sdk.backends.simulated import SimulatedBackend
from kvtracker_sdk.backends.simulated_scene import Cuboid, GroundTruth, SimulatedScene, orbit
from kvtracker_sdk.backends.simulated_sensors import gravity_reading, sensor_depth
from kvtracker_sdk.cache.keyframe_map import KeyframeMap
from kvtracker_sdk.config import TrackerConfig
from kvtracker_sdk.geometry.se3 import project_to_rotation
from kvtracker_sdk.geometry.sim3 import umeyama_alignment
from kvtracker_sdk.tracking.core.events import WorldFrameChangedEvent
from kvtracker_sdk.tracking.facade.tracker import Tracker
from kvtracker_sdk.types import FrameResult

RESULTS = Path(__file__).parent / "results"
TUM = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "tum_fr2_desk"
SIZE = (196, 252)  # Pi3's model size at resolution 224 for 4:3 frames: no resize
UP = np.array([0.0, 0.0, 1.0])  # the simulated world's true up
WINDOW = 100  # frames per window of the world-up measurement


def box_scene(scene: SimulatedScene, half_extents: tuple[float, float, float]) -> SimulatedScene:
    """The simulated room with an upright box (a ``Cuboid``, ``half_extents`` metres along the
    world axes, centred where the sphere would be) as the object: an object with edges, like a
    mug or a carton, whose visible outline is its true extent (a sphere's is not: its outermost
    pixels see the surface at a grazing angle, nearer than the rim)."""
    shape = Cuboid(scene.object_centre, np.array(half_extents))
    return replace(scene, object_radius=shape.radius, object_shape=shape)


def tum_truth() -> GroundTruth:
    return GroundTruth.from_tum(TUM / "groundtruth.txt")


def world_units_per_metre(backend: SimulatedBackend, kf_map: KeyframeMap) -> float:
    """Exact from the simulation: the map's pass answered in its hidden scale, the gauge maps it
    into the world."""
    hidden, _ = backend.read_cache(kf_map.cache)
    return float(kf_map.gauge.scale * hidden.scale)


@dataclass
class Drive:
    """What a run recorded: results, truth, and the world scale of every installed map."""

    results: list[FrameResult] = field(default_factory=list)
    truth: list[np.ndarray] = field(default_factory=list)
    scales: list[tuple[int, int, float]] = field(default_factory=list)  # (frame, generation, u/m)
    world_events: list[WorldFrameChangedEvent] = field(default_factory=list)

    def valid(self) -> tuple[np.ndarray, np.ndarray]:
        """([N, 4, 4] estimated, [N, 4, 4] true) poses of the frames with a valid pose."""
        pairs = [(r.pose.T_world_cam, t) for r, t in zip(self.results, self.truth, strict=True)
                 if r.pose_valid and r.pose is not None]
        return np.array([p for p, _ in pairs]), np.array([t for _, t in pairs])


def drive(
    backend: SimulatedBackend, *, frames: int, depth_every: int = 0, gravity: bool = False,
    reload_at: int | None = None, folder: Path | None = None, seed: int = 1,
    config: dict[str, Any] | None = None, with_mask: bool = False,
    statement: Any = None,
) -> tuple[Drive, Tracker]:
    """Push ``frames`` frames with depth on every ``depth_every``-th (0: none) and gravity
    readings; save and reload the map at frame ``reload_at`` (into ``folder``). ``statement``:
    ``f(tracker, index, run)`` called after each frame (a known size). Returns the record and the
    (open) tracker."""
    cfg = TrackerConfig(resolution=224, **(config or {}))
    tracker = Tracker(cfg, backend)
    run = Drive()
    tracker.events.on_world_frame_changed(run.world_events.append)
    generation = 0
    for frame in backend.frames(SIZE, stop=frames, textured=False, with_mask=with_mask):
        index = frame.index
        if reload_at is not None and index == reload_at:
            assert folder is not None
            path = folder / "reload.kvmap"
            tracker.save_map(path)
            tracker.close()
            tracker = Tracker.from_map(path, backend)
            tracker.events.on_world_frame_changed(run.world_events.append)
        rng = np.random.default_rng((seed, index))
        depth = (sensor_depth(backend.scene, frame.T_world_cam, SIZE, rng=rng)
                 if depth_every and index % depth_every == 0 else None)
        reading = gravity_reading(frame.T_world_cam, rng=rng) if gravity else None
        result = tracker.push_frame(frame.image, timestamp=frame.timestamp, mask=frame.mask,
                                    depth=depth, gravity=reading)
        if statement is not None:
            statement(tracker, index, run)
            result = _with_current_pose(tracker, result)
        run.results.append(result)
        run.truth.append(frame.T_world_cam)
        kf_map = tracker.keyframe_map
        if kf_map is not None and kf_map.generation != generation:
            generation = kf_map.generation
            run.scales.append((index, generation, world_units_per_metre(backend, kf_map)))
    return run, tracker


def _with_current_pose(tracker: Tracker, result: FrameResult) -> FrameResult:
    """The frame's pose re-expressed if a statement changed the world after it was returned."""
    tracked = tracker.get_tracked_pose()
    if tracked is None or tracked.frame_index != result.frame_index or result.pose is None:
        return result
    return replace(result, pose=tracked.pose)


def ate(estimated: np.ndarray, truth: np.ndarray, *, with_scale: bool) -> float:
    """RMSE of the camera centres after a Sim(3) (``with_scale``) or SE(3) alignment."""
    est, gt = estimated[:, :3, 3], truth[:, :3, 3]
    aligned = umeyama_alignment(est, gt, with_scale=with_scale).apply_to_points(est)
    return float(np.sqrt(np.mean(np.sum((aligned - gt) ** 2, axis=1))))


def up_errors_deg(estimated: np.ndarray, truth: np.ndarray) -> tuple[list[float], float]:
    """(tilt of the world's z from true up per window of WINDOW frames, median per frame)."""
    def tilt(R_est_true: np.ndarray) -> float:
        up = R_est_true @ UP
        return float(np.degrees(np.arccos(np.clip(up[2], -1.0, 1.0))))

    rotations = estimated[:, :3, :3] @ np.transpose(truth[:, :3, :3], (0, 2, 1))
    windows = [tilt(project_to_rotation(rotations[i:i + WINDOW].sum(axis=0)))
               for i in range(0, len(rotations) - WINDOW // 2, WINDOW)]
    return windows, float(np.median([tilt(R) for R in rotations]))


def scale_errors(run: Drive) -> dict[str, float]:
    errors = [abs(units - 1.0) for _, _, units in run.scales]
    return {"after_first_map": errors[0], "end": errors[-1], "max": max(errors),
            "maps": len(errors)}


def ros_map_up_errors_deg(run: Drive, kf_map: KeyframeMap | None, folder: Path) -> dict[str, Any]:
    """Write the run as a ROS 2 bag, read the TF back, and measure the map frame's tilt."""
    from rosbags.highlevel import AnyReader

    from kvtracker_sdk.geometry.se3 import rotation_from_quat_xyzw
    from kvtracker_sdk.io.exports.ros2_bag import write_ros2_bag
    from kvtracker_sdk.io.exports.ros_frames import DEFAULT_T_BASE_OPTICAL

    path = folder / "run_bag"
    write_ros2_bag(path, run.results, kf_map, image_size=(SIZE[1], SIZE[0]))
    transforms: dict[int, dict[str, np.ndarray]] = {}
    with AnyReader([path]) as reader:
        for connection, time_ns, raw in reader.messages():
            if connection.topic != "/tf":
                continue
            for item in reader.deserialize(raw, connection.msgtype).transforms:
                q, t = item.transform.rotation, item.transform.translation
                T = np.eye(4)
                T[:3, :3] = rotation_from_quat_xyzw(np.array([q.x, q.y, q.z, q.w]))
                T[:3, 3] = [t.x, t.y, t.z]
                transforms.setdefault(time_ns, {})[item.child_frame_id] = T
    truth_by_ns = {int(round(r.timestamp * 1e9)): t for r, t in zip(run.results, run.truth,
                                                                    strict=True)}
    est, gt = [], []
    for stamp, frames in sorted(transforms.items()):
        T_map_cam = frames["odom"] @ frames["base_link"] @ DEFAULT_T_BASE_OPTICAL
        est.append(T_map_cam)
        gt.append(truth_by_ns[stamp])
    windows, per_frame = up_errors_deg(np.array(est), np.array(gt))
    return {"poses": len(est), "map_up_error_deg_max_window": max(windows),
            "map_up_error_deg_median_frame": per_frame}


def run_rgbd(truth: GroundTruth, frames: int, folder: Path, *, gravity: bool,
             reload_at: int | None, depth_every: int = 1,
             config: dict[str, Any] | None = None,
             ) -> tuple[dict[str, Any], Drive, KeyframeMap | None]:
    """Depth (every ``depth_every``-th frame) and maybe gravity, saved and reloaded at
    ``reload_at``: the row of numbers, the record, and the final map."""
    backend = SimulatedBackend(truth)
    start = time.perf_counter()
    run, tracker = drive(backend, frames=frames, depth_every=depth_every, gravity=gravity,
                         reload_at=reload_at, folder=folder, config=config)
    elapsed = time.perf_counter() - start
    est, gt = run.valid()
    status = tracker.map_status
    kf_map = tracker.keyframe_map
    tracker.close()
    row: dict[str, Any] = {
        "frames": frames, "valid": len(est), "reload_at": reload_at, "depth_every": depth_every,
        "scale_error": scale_errors(run),
        "ate_m_se3": ate(est, gt, with_scale=False),
        "world": status.world.to_dict(),
        "scale_estimates": [
            {"source": e.source.value, "metres_per_unit": e.metres_per_unit,
             "relative_uncertainty": e.relative_uncertainty, "samples": e.samples}
            for e in status.scale_estimates],
        "world_events": [e.reason.value for e in run.world_events],
        "seconds": elapsed,
    }
    if gravity:
        windows, per_frame = up_errors_deg(est, gt)
        row["up_error_deg_windows"] = windows
        row["up_error_deg_max_window"] = max(windows)
        row["up_error_deg_median_frame"] = per_frame
        assert status.gravity is not None
        row["gravity_uncertainty_deg"] = status.gravity.uncertainty_deg
        row["heading_error_deg"] = heading_error_deg(est, gt)
    return row, run, kf_map


def heading_error_deg(estimated: np.ndarray, truth: np.ndarray) -> float:
    """Angle between the world's x axis and keyframe 0's viewing direction made horizontal (the
    levelled world keeps keyframe 0's yaw), both in the estimated world, over the last window."""
    R = project_to_rotation((estimated[-WINDOW:, :3, :3]
                             @ np.transpose(truth[-WINDOW:, :3, :3], (0, 2, 1))).sum(axis=0))
    forward = R @ truth[0, :3, 2]  # keyframe 0's true viewing direction, in the estimated world
    forward[2] = 0.0
    forward /= np.linalg.norm(forward)
    return float(np.degrees(np.arccos(np.clip(forward[0], -1.0, 1.0))))


def run_mono(truth: GroundTruth, frames: int) -> dict[str, Any]:
    """RGB only: the world's scale and the Sim(3)-aligned ATE."""
    backend = SimulatedBackend(truth)
    run, tracker = drive(backend, frames=frames)
    tracker.close()
    est, gt = run.valid()
    return {"frames": frames, "valid": len(est), "world_units_per_metre": run.scales[0][2],
            "ate_m_sim3": ate(est, gt, with_scale=True)}


def object_backend(shape: str) -> tuple[SimulatedBackend, float]:
    """(backend orbiting the object, its true height in metres): ``sphere`` (0.6 m) or ``box``
    (0.5 m tall)."""
    truth = orbit(720)
    noise = {"seed": 2, "translation_noise_m": 0.003, "rotation_noise_deg": 0.1}
    if shape == "sphere":
        backend = SimulatedBackend(truth, **noise)  # type: ignore[arg-type]
        return backend, 2.0 * backend.scene.object_radius
    box = box_scene(SimulatedScene.around(truth.poses), (0.2, 0.15, 0.25))
    return SimulatedBackend(truth, scene=box, **noise), 0.5  # type: ignore[arg-type]


def run_object_height(shape: str, frames: int = 720, *, gravity: bool = True) -> dict[str, Any]:
    """Object mode around the object, its true height stated after frame 0 (``gravity``: with
    accelerometer readings, so that "height" is along the true up; without, it is along keyframe
    0's image up, which a camera looking down at a box tilts into the box's depth)."""
    backend, height = object_backend(shape)

    def state(tracker: Tracker, index: int, _run: Drive) -> None:
        if index == 0:
            tracker.world.set_object_height(height)

    run, tracker = drive(backend, frames=frames, config={"mode": "object"}, with_mask=True,
                         statement=state, gravity=gravity)
    status = tracker.map_status
    tracker.close()
    errors = scale_errors(run)
    after = [units for frame, _, units in run.scales if frame == 0][-1]  # after the rescale
    return {"shape": shape, "frames": frames, "gravity": gravity, "true_height_m": height,
            "scale_error_after_statement":
            abs(after - 1.0), "scale_error_end": errors["end"], "scale_error_max": errors["max"],
            "estimate": [{"source": e.source.value, "relative_uncertainty":
                          e.relative_uncertainty} for e in status.scale_estimates]}


def run_known_distance(truth: GroundTruth, frames: int, distance_frame: int) -> dict[str, Any]:
    """The true distance between the camera centres of frames 0 and ``distance_frame`` stated
    at ``distance_frame``."""
    backend = SimulatedBackend(truth)
    truth = backend.ground_truth.poses
    first: list[Any] = []

    def state(tracker: Tracker, index: int, run: Drive) -> None:
        if index == 0:
            first.append(tracker.get_tracked_pose())
        if index == distance_frame:
            length = float(np.linalg.norm(truth[distance_frame, :3, 3] - truth[0, :3, 3]))
            tracker.world.set_known_distance(length, first[0], tracker.get_tracked_pose())

    run, tracker = drive(backend, frames=frames, statement=state)
    tracker.close()
    after = [u for frame, _, u in run.scales if frame == distance_frame][-1]
    return {"frames": frames, "distance_frame": distance_frame,
            "true_distance_m": float(np.linalg.norm(truth[distance_frame, :3, 3] - truth[0, :3, 3])),
            "scale_error_after_statement": abs(after - 1.0),
            "scale_error_end": scale_errors(run)["end"]}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=2981)
    parser.add_argument("--out", type=Path, default=RESULTS / "metric_world.json")
    args = parser.parse_args(argv)
    frames = args.frames
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        truth = tum_truth()
        mono = run_mono(truth, frames)
        rgbd, _, _ = run_rgbd(truth, frames, folder, gravity=False, reload_at=frames // 2)
        (folder / "gravity").mkdir()
        gravity, run, kf_map = run_rgbd(truth, frames, folder / "gravity", gravity=True,
                                        reload_at=frames // 2)
        gravity["ros2_bag"] = ros_map_up_errors_deg(run, kf_map, folder)
        known = {"object_height_box": run_object_height("box"),
                 "object_height_sphere": run_object_height("sphere"),
                 "distance": run_known_distance(truth, min(frames, 1200), min(frames, 1200) - 1)}
    report = {
        "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs",
        "load_1min": os.getloadavg()[0],
        "command": "python -m benchmarks.metric_world " + " ".join(argv or sys.argv[1:]),
        "mono": mono, "rgbd": rgbd, "rgbd_gravity": gravity, "known_size": known,
        "ate_ratio_rgbd_over_mono_sim3": rgbd["ate_m_se3"] / mono["ate_m_sim3"],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(table(report))
    return report


def table(report: dict[str, Any]) -> str:
    mono, rgbd, grav = report["mono"], report["rgbd"], report["rgbd_gravity"]
    known = report["known_size"]
    lines = [
        "| run | scale error after first map | at end | max | ATE (m) | up error (deg) |",
        "|---|---|---|---|---|---|",
        f"| mono | world {mono['world_units_per_metre']:.3f} units/m | | | "
        f"{mono['ate_m_sim3']:.4f} (Sim(3)) | |",
    ]
    for name, row in (("rgbd", rgbd), ("rgbd + gravity", grav)):
        s = row["scale_error"]
        up = f"{row['up_error_deg_max_window']:.3f} (max window)" if "up_error_deg_max_window" \
            in row else ""
        lines.append(f"| {name} | {100 * s['after_first_map']:.3f} % | {100 * s['end']:.3f} % | "
                     f"{100 * s['max']:.3f} % | {row['ate_m_se3']:.4f} (SE(3)) | {up} |")
    for shape in ("box", "sphere"):
        row = known[f"object_height_{shape}"]
        lines.append(f"| object height ({row['true_height_m']:.1f} m {shape}) | "
                     f"{100 * row['scale_error_after_statement']:.2f} % | "
                     f"{100 * row['scale_error_end']:.2f} % | | | |")
    lines.append(f"| known distance | "
                 f"{100 * known['distance']['scale_error_after_statement']:.2f} % | "
                 f"{100 * known['distance']['scale_error_end']:.2f} % | | | |")
    lines.append(f"\nATE rgbd / mono (Sim(3)): {report['ate_ratio_rgbd_over_mono_sim3']:.3f}; "
                 f"ROS 2 bag map z tilt (max window): "
                 f"{grav['ros2_bag']['map_up_error_deg_max_window']:.3f} deg")
    return "\n".join(lines)


if __name__ == "__main__":
    main()

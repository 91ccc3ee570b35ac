"""The files a ``kvtracker track`` / ``demo`` run writes into ``--out``.

| file | content |
|---|---|
| ``trajectory.txt`` | TUM: every frame with a valid pose, ``T_world_cam``, stamps in full precision |
| ``keyframes.json`` | the map's keyframes: id, source frame, stamp, ``T_world_cam``, confidence |
| ``points.ply`` | the map's fused point cloud, confidence-filtered and voxel-thinned (binary PLY) |
| ``trajectory.png`` | the trajectory on three planes (and against the ground truth, with errors) |
| ``groundtruth.txt`` | (demo) the simulated camera's true trajectory, TUM |
| ``object.json`` | (object mode) the object's frame and extent, each frame's region and ``T_cam_object`` |
| ``evaluation.json`` | (when ground truth is known) ATE / RPE / cm-degree report |
| ``run.json`` | what ran: command, input, config, versions, backend fingerprint, timings, states |

Every file is written atomically (``io/``'s writers), ``run.json`` last: a folder with a
``run.json`` holds a complete run. An optional output whose extra is missing (the plot without
matplotlib) is skipped with a warning and listed under ``skipped_outputs``; it never costs the
others. Files of ours that a previous run listed in the folder's ``run.json`` and this run did
not write (e.g. its ``evaluation.json``) are removed, so the folder holds one run only.
"""

from __future__ import annotations

import json
import platform
import sys
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from kvtracker_sdk._version import __version__
from kvtracker_sdk.cli.object_outputs import object_document
from kvtracker_sdk.errors import EvaluationError, MissingDependencyError
from kvtracker_sdk.io.exports.ply import write_ply
from kvtracker_sdk.io.files.atomic import atomic_write
from kvtracker_sdk.io.files.trajectory import Trajectory, write_tum
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.runs.run_loop import RunRecord

if TYPE_CHECKING:
    from kvtracker_sdk.cache.keyframe_map import KeyframeMap
    from kvtracker_sdk.eval.report import EvaluationReport
    from kvtracker_sdk.tracking.facade.tracker import Tracker

__all__ = ["RunDescription", "RunOutputs", "auto_voxel_size", "write_outputs"]

_log = get_logger(__name__)
_VERSIONED = ("numpy", "torch", "onnxruntime", "rerun-sdk", "opencv-python-headless", "typer")
_AUTO_VOXEL_FRACTION = 0.005  # of keyframe 0's median depth: ~1.5 mm at 30 cm, 1 cm at 2 m
# the files a run writes into --out by these names (others in the folder are never touched)
_OUR_FILES = frozenset({"trajectory.txt", "keyframes.json", "points.ply", "trajectory.png",
                        "groundtruth.txt", "evaluation.json", "object.json"})


@dataclass(frozen=True)
class RunDescription:
    """What a run was, for ``run.json`` (the record and the tracker supply the rest)."""

    command: str  # "track" or "demo"
    input: str
    simulated: bool
    argv: list[str] = field(default_factory=lambda: list(sys.argv))
    details: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class RunOutputs:
    """The files written (name -> path) and, with ground truth, the evaluation."""

    files: dict[str, Path]
    num_poses: int
    num_points: int
    evaluation: EvaluationReport | None
    skipped: dict[str, str] = field(default_factory=dict)  # output -> why it was not written


def auto_voxel_size(keyframe_map: KeyframeMap) -> float | None:
    """A voxel edge scaled to the scene: a fraction of keyframe 0's median confident depth.

    The world frame's scale is the first mapping pass's (monocular: unknown), so a fixed size in
    metres would be meaningless; None when keyframe 0 has no confident depth.
    """
    kf = keyframe_map.keyframes[0]
    depth = kf.local_points[..., 2][(kf.confidence_map >= 0.5) & (kf.local_points[..., 2] > 0)]
    depth = depth[np.isfinite(depth)]
    return float(np.median(depth)) * _AUTO_VOXEL_FRACTION if depth.size else None


def write_outputs(
    out_dir: Path,
    tracker: Tracker,
    record: RunRecord,
    description: RunDescription,
    *,
    ground_truth: Trajectory | None = None,
    write_ground_truth: bool = False,
    min_confidence: float = 0.5,
    voxel_size: float | None = None,
    extra_files: dict[str, Path] | None = None,
    skipped: dict[str, str] | None = None,
) -> RunOutputs:
    """Write every output of a run into ``out_dir`` (created); ``voxel_size`` None: automatic,
    0: no thinning. ``ground_truth`` enables the evaluation and the comparison plot;
    ``extra_files`` (e.g. the rerun recording) are listed in ``run.json``, as are the outputs
    ``skipped`` before (name -> reason) and here."""
    skipped = dict(skipped or {})
    out_dir.mkdir(parents=True, exist_ok=True)
    files = {name: out_dir / name for name in ("trajectory.txt", "keyframes.json", "points.ply")}
    trajectory = record.trajectory()
    write_tum(files["trajectory.txt"], trajectory)
    keyframe_map = tracker.keyframe_map
    _write_json(files["keyframes.json"], _keyframes_document(keyframe_map))
    num_points = _write_points(files["points.ply"], keyframe_map, min_confidence, voxel_size)
    if tracker.config.mode.value == "object":
        files["object.json"] = out_dir / "object.json"
        _write_json(files["object.json"], object_document(tracker, record.results))
    if ground_truth is not None and write_ground_truth:
        files["groundtruth.txt"] = out_dir / "groundtruth.txt"
        write_tum(files["groundtruth.txt"], ground_truth)
    evaluation, evaluation_note = None, None
    if ground_truth is not None:
        evaluation, evaluation_note = _evaluate(trajectory, ground_truth)
        if evaluation is not None:
            files["evaluation.json"] = out_dir / "evaluation.json"
            _write_json(files["evaluation.json"], evaluation.to_dict())
    if not len(trajectory):
        skipped["trajectory.png"] = "no valid pose"
    else:
        try:
            files["trajectory.png"] = _plot(out_dir / "trajectory.png", trajectory, evaluation,
                                            description)
        except MissingDependencyError as error:  # an optional output: the others still matter
            skipped["trajectory.png"] = str(error)
    for name, reason in skipped.items():
        _log.warning(f"{name} not written", reason=reason)
    files.update(extra_files or {})
    _remove_stale_outputs(out_dir, written=set(files))
    files["run.json"] = out_dir / "run.json"
    document = _run_document(tracker, record, description, files, num_points, evaluation,
                             evaluation_note)
    document["skipped_outputs"] = skipped
    _write_json(files["run.json"], document)
    return RunOutputs(files, len(trajectory), num_points, evaluation, skipped)


def _remove_stale_outputs(out_dir: Path, written: set[str]) -> None:
    """Remove the files of ours that the folder's previous ``run.json`` lists and this run did
    not write: only our own names, only directly in ``out_dir``, only if listed there."""
    previous = out_dir / "run.json"
    try:
        listed = json.loads(previous.read_text(encoding="utf-8")).get("outputs", {})
    except (OSError, ValueError, AttributeError):  # no previous run (or not one of ours)
        return
    if not isinstance(listed, dict):
        return
    for name, path in listed.items():
        target = out_dir / str(name)
        if name in _OUR_FILES and name not in written and Path(str(path)).name == name:
            try:
                if target.is_file() and Path(str(path)).resolve() == target.resolve():
                    target.unlink()
                    _log.info("removed an output of the previous run", path=str(target))
            except OSError as error:
                _log.warning("cannot remove an output of the previous run", path=str(target),
                             reason=str(error))


def _write_json(path: Path, document: Any) -> None:
    with atomic_write(path) as handle:
        json.dump(document, handle, indent=2, allow_nan=False)
        handle.write("\n")


def _keyframes_document(keyframe_map: KeyframeMap | None) -> dict[str, Any]:
    if keyframe_map is None:
        return {"generation": 0, "resolution": None, "keyframes": []}
    return {
        "generation": keyframe_map.generation,
        "resolution": list(keyframe_map.resolution),  # (H, W) of the model input
        "pose_convention": "T_world_cam (camera-to-world), OpenCV axes, 4x4 row-major",
        "keyframes": [
            {
                "keyframe_id": kf.keyframe_id,
                "frame_index": kf.frame_index,
                "timestamp": kf.timestamp,
                "T_world_cam": kf.T_world_cam.tolist(),
                "mean_confidence": kf.mean_confidence,
                "has_mask": kf.mask is not None,
            }
            for kf in keyframe_map.keyframes
        ],
    }


def _write_points(
    path: Path, keyframe_map: KeyframeMap | None, min_confidence: float, voxel_size: float | None
) -> int:
    if keyframe_map is None:  # no map was built: an empty cloud keeps the folder's layout fixed
        write_ply(path, np.zeros((0, 3)), comment="kvtracker: no map was built")
        return 0
    from kvtracker_sdk.io.exports.map_export import (
        export_point_cloud,  # loads torch (the map's cache)
    )

    voxel = auto_voxel_size(keyframe_map) if voxel_size is None else (voxel_size or None)
    return export_point_cloud(keyframe_map, path, min_confidence=min_confidence, voxel_size=voxel)


def _evaluate(
    trajectory: Trajectory, ground_truth: Trajectory
) -> tuple[EvaluationReport | None, str | None]:
    from kvtracker_sdk.eval.report import evaluate_trajectories

    try:
        return evaluate_trajectories(trajectory, ground_truth), None
    except EvaluationError as exc:  # e.g. too few valid poses: the run itself still succeeded
        _log.warning("evaluation skipped", reason=str(exc))
        return None, str(exc)


def _plot(
    path: Path,
    trajectory: Trajectory,
    evaluation: EvaluationReport | None,
    description: RunDescription,
) -> Path:
    from kvtracker_sdk.eval.plots import plot_trajectory

    label = "SIMULATED " if description.simulated else ""
    if evaluation is None:  # the first mapping pass's scale: monocular, not metres
        return plot_trajectory(path, trajectory, title=f"kvtracker {label}{description.command}",
                               units=None)
    ate = evaluation.ate
    return plot_trajectory(
        path,
        evaluation.aligned_estimate,
        evaluation.association.ref,
        translation_errors=ate.translation_errors,
        title=f"kvtracker {label}{description.command}: ATE RMSE {ate.translation.rmse:.4f} "
        f"({ate.alignment.value} aligned)",
        # scaled onto the ground truth (metres in TUM, 7-Scenes and the demo) only by a Sim(3)
        units="m" if ate.alignment.value == "sim3" else None,
    )


def _versions() -> dict[str, str | None]:
    versions: dict[str, str | None] = {
        "kvtracker-sdk": __version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
    }
    for name in _VERSIONED:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def _run_document(
    tracker: Tracker,
    record: RunRecord,
    description: RunDescription,
    files: dict[str, Path],
    num_points: int,
    evaluation: EvaluationReport | None,
    evaluation_note: str | None,
) -> dict[str, Any]:
    info = tracker.backend.info
    status = tracker.map_status
    return {
        "command": description.command,
        "simulated": description.simulated,
        "input": description.input,
        "argv": description.argv,
        "details": description.details,
        "versions": _versions(),
        "backend": {
            "runtime": info.backend, "model": info.model, "family": info.family,
            "fingerprint": info.fingerprint, "weights_fingerprint": info.weights_fingerprint,
            "config_hash": info.config_hash, "dtype": info.dtype, "device": info.device,
            "accelerations": list(info.accelerations),
        },
        "config": tracker.config.to_dict(),
        "frames": record.num_frames,
        "valid_poses": int(sum(r.pose_valid for r in record.results)),
        "interrupted": record.interrupted,
        "stopped_by": None if record.failure is None else (
            f"{type(record.failure).__name__}: {record.failure}"
        ),
        "bad_frames": record.bad_frames_document(),
        "wall_seconds": round(record.wall_seconds, 4),
        "fps": round(record.fps, 3),
        "timings": {name: s.to_dict() for name, s in record.stage_stats().items()},
        "states_visited": record.states_visited(),
        "frames_per_state": record.frames_per_state(),
        "state_changes": [
            {"frame_index": c.frame_index, "from": c.previous.value, "to": c.state.value,
             "reason": c.reason.value}
            for c in record.state_changes
        ],
        "map": {"keyframes": status.num_keyframes, "generation": status.generation,
                "cache_bytes": status.cache_bytes, "points": num_points},
        "evaluation": (
            evaluation.to_dict() if evaluation is not None
            else {"skipped": evaluation_note} if evaluation_note else None
        ),
        "outputs": {name: str(path) for name, path in sorted(files.items())},
    }

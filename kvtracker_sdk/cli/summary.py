"""The short report printed (to stdout) at the end of ``kvtracker track`` / ``demo``, e.g.::

    kvtracker track: 20 frames in 1.6 s (12.5 FPS)
    states     INIT -> MAPPING -> TRACKING   (frames: TRACKING 20)
    keyframes  4 (map generation 4, cache 2.0 MB)
    poses      20 valid of 20; 90275 map points
    time/frame source 18.4 ms | preprocess 3.5 ms | track 31.9 ms (x19) | map 66.0 ms (x4) | ...
    accuracy   ATE RMSE 0.0886 m (sim3 aligned, 20 poses), RPE 0.0508 m / 3.83 deg
    outputs    run/ (evaluation.json, keyframes.json, points.ply, run.json, trajectory.png, ...)
"""

from __future__ import annotations

from pathlib import Path

from kvtracker_sdk.cli.outputs import RunOutputs
from kvtracker_sdk.runs.run_loop import RunRecord
from kvtracker_sdk.types import MapStatus

__all__ = ["format_summary"]

# stages in pipeline order; the tracker's "total" (all of push_frame) is shown as "push_frame"
_STAGE_ORDER = ("source", "preprocess", "track", "map", "total", "sink")
_STAGE_LABELS = {"total": "push_frame"}


def format_summary(
    command: str,
    record: RunRecord,
    status: MapStatus,
    outputs: RunOutputs,
    out_dir: Path,
    *,
    simulated: bool = False,
) -> str:
    """The end-of-run report as text lines (no trailing newline)."""
    label = f"kvtracker {command}" + (" [SIMULATED: poses from a noisy known path]" if simulated else "")
    ended = " - interrupted" if record.interrupted else ""
    per_state = ", ".join(f"{state} {count}" for state, count in record.frames_per_state().items())
    lines = [
        f"{label}: {record.num_frames} frames in {record.wall_seconds:.1f} s "
        f"({record.fps:.1f} FPS){ended}",
        f"states     {' -> '.join(record.states_visited())}   (frames: {per_state or 'none'})",
        f"keyframes  {status.num_keyframes} (map generation {status.generation}, "
        f"cache {status.cache_bytes / 1e6:.1f} MB)",
        f"poses      {outputs.num_poses} valid of {record.num_frames}; "
        f"{outputs.num_points} map points",
        f"time/frame {_stages(record)}",
    ]
    if outputs.evaluation is not None:
        ate, rpe = outputs.evaluation.ate, outputs.evaluation.rpe
        lines.append(
            f"accuracy   ATE RMSE {ate.translation.rmse:.4f} m ({ate.alignment.value} aligned, "
            f"{len(outputs.evaluation.association)} poses), RPE {rpe.translation.rmse:.4f} m / "
            f"{rpe.rotation_deg.rmse:.2f} deg"
        )
    if record.bad_frames:
        first = record.bad_frames[0]
        verb = "stopped the run" if record.failure is not None else "skipped"
        lines.append(f"bad frames {len(record.bad_frames)} {verb} (--on-bad-frame "
                     f"{record.bad_frame_policy.value}); first at position {first.position}: "
                     f"{first.error}")
    elif record.failure is not None:
        lines.append(f"stopped    {type(record.failure).__name__}: {record.failure}")
    names = ", ".join(sorted(path.name for path in outputs.files.values()))
    lines.append(f"outputs    {out_dir}/ ({names})")
    for name, reason in outputs.skipped.items():
        lines.append(f"warning    {name} not written: {reason}")
    return "\n".join(lines)


def _stages(record: RunRecord) -> str:
    """Mean milliseconds per stage; stages that ran on few frames (map) show their count."""
    stats = record.stage_stats()
    names = [n for n in _STAGE_ORDER if n in stats] + sorted(set(stats) - set(_STAGE_ORDER))
    parts = []
    for name in names:
        s = stats[name]
        count = f" (x{s.count})" if s.count < record.num_frames else ""
        parts.append(f"{_STAGE_LABELS.get(name, name)} {s.mean_ms:.1f} ms{count}")
    return " | ".join(parts) or "n/a"

"""One tracking run from frames to files: the part ``kvtracker track`` and ``demo`` share.

Opens the optional rerun recording, runs the frame loop under the live progress bar, writes the
outputs, prints the summary, and turns a Ctrl-C into exit code 130 after the outputs of the
frames processed so far are written. A run that fails discards its half-made recording.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from kvtracker_sdk.cli.failures import ExitCode
from kvtracker_sdk.cli.logging_setup import CliState
from kvtracker_sdk.cli.outputs import RunDescription, RunOutputs, write_outputs
from kvtracker_sdk.cli.progress import FrameProgress
from kvtracker_sdk.cli.run_loop import InputFrame, RunRecord, run_frames
from kvtracker_sdk.cli.summary import format_summary
from kvtracker_sdk.io.trajectory import Trajectory
from kvtracker_sdk.log import get_logger

if TYPE_CHECKING:
    from kvtracker_sdk.tracking.events import StateChangeEvent
    from kvtracker_sdk.tracking.tracker import Tracker

__all__ = ["OutputOptions", "run_session"]

_log = get_logger(__name__)


@dataclass(frozen=True)
class OutputOptions:
    """Where and how a run writes its results."""

    out_dir: Path
    rerun: Path | None = None
    min_confidence: float = 0.5
    voxel_size: float | None = None  # None: automatic; 0: keep every point
    ground_truth: Trajectory | None = None
    write_ground_truth: bool = False


def run_session(
    state: CliState,
    tracker: Tracker,
    frames: Iterable[InputFrame],
    *,
    total: int | None,
    description: RunDescription,
    options: OutputOptions,
    announce_states: bool = False,
) -> tuple[RunRecord, RunOutputs]:
    """Track ``frames``, write every output, print the summary; returns what happened."""
    from kvtracker_sdk.viz.rerun_sink import RerunSink

    options.out_dir.mkdir(parents=True, exist_ok=True)  # fail before tracking, not after
    sink = None
    if options.rerun is not None:
        application = "kvtracker-SIMULATED" if description.simulated else "kvtracker"
        sink = RerunSink(options.rerun, application_id=application,
                         min_confidence=options.min_confidence)
    try:
        if sink is not None:
            sink.attach(tracker)
            sink.log_map(tracker.keyframe_map)  # a map loaded before the run (None otherwise)
        with FrameProgress(
            state.console, total, label=description.command, enabled=state.chatty
        ) as progress:

            def announce(event: StateChangeEvent) -> None:
                if announce_states and state.chatty:
                    where = "reset" if event.frame_index is None else f"frame {event.frame_index:>5}"
                    progress.note(
                        f"{where}: {event.previous.value} -> {event.state.value} "
                        f"({event.reason.value})"
                    )

            record = run_frames(
                tracker,
                frames,
                progress,
                before_frame=(lambda i, f: sink.set_time(i, f.timestamp)) if sink else None,
                after_frame=(lambda _i, f, r: sink.log_frame(f.image, r)) if sink else None,
                on_state_change=announce,
            )
    except BaseException:
        if sink is not None:
            sink.close(keep=False)
        raise
    extra_files: dict[str, Path] = {}
    if sink is not None and options.rerun is not None:
        sink.close()  # the recording is complete: keep it even if writing the files fails
        extra_files["rerun"] = options.rerun
    outputs = write_outputs(
        options.out_dir,
        tracker,
        record,
        description,
        ground_truth=options.ground_truth,
        write_ground_truth=options.write_ground_truth,
        min_confidence=options.min_confidence,
        voxel_size=options.voxel_size,
        extra_files=extra_files,
    )
    _report(state, description, record, outputs, tracker, options.out_dir)
    if record.interrupted:
        raise typer.Exit(int(ExitCode.INTERRUPTED))
    return record, outputs


def _report(
    state: CliState,
    description: RunDescription,
    record: RunRecord,
    outputs: RunOutputs,
    tracker: Tracker,
    out_dir: Path,
) -> None:
    status = tracker.map_status
    _log.info(
        "run finished", command=description.command, frames=record.num_frames,
        keyframes=status.num_keyframes, valid_poses=outputs.num_poses, fps=round(record.fps, 2),
        simulated=description.simulated, interrupted=record.interrupted, out=str(out_dir),
    )
    if not state.quiet:
        typer.echo(format_summary(description.command, record, status, outputs, out_dir,
                                  simulated=description.simulated))

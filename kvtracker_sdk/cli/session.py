"""One tracking run from frames to files: the part ``kvtracker track`` and ``demo`` share.

Checks every output location before the first frame (``check_outputs``), opens the optional
rerun recording, runs the frame loop under the live progress bar, then keeps whatever the frames
gave: the map (``--save-map``) first, then the files of ``--out``, the summary, and only then the
exit status. A Ctrl-C exits 130, a bad frame under ``--on-bad-frame stop`` exits 3, another
failure its own code: each after the map and the outputs of the frames processed are written.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from kvtracker_sdk.cli.failures import ExitCode
from kvtracker_sdk.cli.logging_setup import CliState
from kvtracker_sdk.cli.output_checks import check_output_file, check_output_folder
from kvtracker_sdk.cli.outputs import RunDescription, RunOutputs, write_outputs
from kvtracker_sdk.cli.progress import FrameProgress, busy
from kvtracker_sdk.cli.summary import format_summary
from kvtracker_sdk.errors import KVTrackerError, MapError, MapIOError, OutputError
from kvtracker_sdk.io.files.trajectory import Trajectory
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.runs.run_loop import BadFramePolicy, InputFrame, RunRecord
from kvtracker_sdk.runs.session import track
from kvtracker_sdk.types import FrameResult

if TYPE_CHECKING:
    from kvtracker_sdk.io.map_file.map_format import MapInfo
    from kvtracker_sdk.tracking.core.events import StateChangeEvent
    from kvtracker_sdk.tracking.facade.tracker import Tracker
    from kvtracker_sdk.viz.rerun_sink import RerunSink

__all__ = ["OutputOptions", "check_outputs", "run_session"]

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
    save_map: Path | None = None
    # called after every frame (the live view, the ROS 2 bag: cli/live_outputs.py)
    frame_observers: tuple[Callable[[InputFrame, FrameResult], None], ...] = ()


def check_outputs(options: OutputOptions) -> None:
    """Every output location can be written (``OutputError`` otherwise): call it before
    anything slow (loading weights, the first frame)."""
    check_output_folder(options.out_dir, "--out")
    for path, option in ((options.rerun, "--rerun"), (options.save_map, "--save-map")):
        if path is not None:
            check_output_file(path, option)


def run_session(
    state: CliState,
    tracker: Tracker,
    frames: Iterable[InputFrame],
    *,
    total: int | None,
    description: RunDescription,
    options: OutputOptions,
    announce_states: bool = False,
    on_bad_frame: BadFramePolicy = BadFramePolicy.STOP,
) -> tuple[RunRecord, RunOutputs]:
    """Track ``frames``, save the map, write every output, print the summary; then raise what
    ended the run early (``typer.Exit(130)`` after a Ctrl-C). Returns what happened."""
    from kvtracker_sdk.viz.rerun_sink import RerunSink

    check_outputs(options)  # fail before tracking, not after (the commands call it earlier too)
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

            record = track(
                tracker,
                frames,
                progress=progress,
                before_frame=(lambda i, f: sink.set_time(i, f.timestamp)) if sink else None,
                after_frame=_after_frame(sink, options.frame_observers),
                on_state_change=announce,
                on_bad_frame=on_bad_frame,
            )
    except BaseException:
        if sink is not None:
            sink.close(keep=False)
        raise
    extra_files: dict[str, Path] = {}
    if sink is not None and options.rerun is not None:
        sink.close()  # the recording so far is kept, whatever ended the run
        extra_files["rerun"] = options.rerun
    saved, map_error, skipped = None, None, {}
    if options.save_map is not None:
        complete = record.failure is None and not record.interrupted
        try:
            with busy(state, f"saving the map to {options.save_map}"):
                saved = _save_map(tracker, options.save_map, run_complete=complete)
        except KVTrackerError as error:  # the other outputs are still written
            map_error = error
        if saved is not None:
            extra_files["map"] = options.save_map
        else:
            skipped["map"] = str(map_error or "no map was built")
    try:
        with busy(state, f"writing the outputs to {options.out_dir}"):
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
                skipped=skipped,
            )
    except Exception as error:
        first = record.failure or map_error
        if first is None:
            raise
        _log.error("outputs not written after the run failed", error=str(error))
        raise first from error
    _report(state, description, record, outputs, tracker, options.out_dir)
    if saved is not None and not state.quiet:
        typer.echo(f"map        saved {options.save_map} ({saved.num_keyframes} keyframes, "
                   f"{saved.file_size / 1e6:.1f} MB)")
    for ending in (map_error, record.failure):
        if ending is not None:
            raise ending
    if record.interrupted:
        raise typer.Exit(int(ExitCode.INTERRUPTED))
    return record, outputs


def _save_map(tracker: Tracker, path: Path, *, run_complete: bool) -> MapInfo | None:
    """Save the tracker's map to ``path``; None (a warning) when a run cut short built none."""
    if tracker.keyframe_map is None:
        if run_complete:
            raise MapError(f"no map was built, nothing to save to {path}")
        _log.warning("no map was built before the run ended: --save-map not written",
                     path=str(path))
        return None
    try:
        return tracker.save_map(path)
    except MapIOError as error:  # writing, not reading, failed: an output problem (exit 10)
        raise OutputError(f"--save-map {path}: cannot write the map ({error})") from error


def _after_frame(
    sink: RerunSink | None, observers: tuple[Callable[[InputFrame, FrameResult], None], ...]
) -> Callable[[int, InputFrame, FrameResult], None] | None:
    """The loop's per-frame hook: the rerun sink, then every observer (None without any)."""
    if sink is None and not observers:
        return None

    def after(_index: int, frame: InputFrame, result: FrameResult) -> None:
        if sink is not None:
            sink.log_frame(frame.image, result)
        for observer in observers:
            observer(frame, result)

    return after


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

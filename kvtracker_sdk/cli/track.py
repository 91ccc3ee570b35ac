"""``kvtracker track INPUT``: track a camera (or an object) through a video or an image sequence."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

from kvtracker_sdk.cli.backends import DEFAULT_WEIGHTS, BackendKind, ComputeDtype, open_backend
from kvtracker_sdk.cli.failures import EXIT_CODES_EPILOG, reports_errors
from kvtracker_sdk.cli.inputs import FrameSelection, MaskFolder, parse_bbox, read_frames
from kvtracker_sdk.cli.logging_setup import CliState
from kvtracker_sdk.cli.outputs import RunDescription
from kvtracker_sdk.cli.session import OutputOptions, run_session
from kvtracker_sdk.config import TrackerConfig, TrackingMode
from kvtracker_sdk.errors import ConfigError, MapError

__all__ = ["register", "track"]

_OUT_HELP = "Output folder: trajectory.txt, keyframes.json, points.ply, trajectory.png, run.json."


@reports_errors
def track(
    ctx: typer.Context,
    input_path: Annotated[Path, typer.Argument(
        metavar="INPUT", help="Video file, image folder, TUM folder (rgb.txt) or 7-Scenes sequence.",
        show_default=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help=_OUT_HELP)] = Path("kvtracker_out"),
    weights: Annotated[str, typer.Option(
        help="Checkpoint: a .safetensors file, a folder holding one, or a hub id.")] = DEFAULT_WEIGHTS,
    backend: Annotated[BackendKind, typer.Option(help="Inference runtime.")] = BackendKind.TORCH,
    device: Annotated[str, typer.Option(help="cpu, cuda, cuda:1, ...")] = "cpu",
    dtype: Annotated[ComputeDtype, typer.Option(help="Compute dtype (torch).")] = ComputeDtype.FLOAT32,
    threads: Annotated[int | None, typer.Option(
        help="CPU threads for inference (torch). [default: torch's choice]")] = None,
    resolution: Annotated[int | None, typer.Option(
        help="Model input side d (224, 308 or 518): at most d² pixels. [default: 308]")] = None,
    mode: Annotated[TrackingMode | None, typer.Option(
        help="scene: the camera in a static scene; object: a masked object. [default: scene]")] = None,
    masks: Annotated[Path | None, typer.Option(
        help="Object mode: folder with one mask image per frame (natural order).")] = None,
    bbox: Annotated[str | None, typer.Option(
        help="Object mode: x0,y0,x1,y1 box (pixels) used for every frame.")] = None,
    keyframe_interval: Annotated[int | None, typer.Option(
        help="Scene mode: a keyframe every N frames. [default: 50]")] = None,
    view_angle: Annotated[float | None, typer.Option(
        help="Object mode: new keyframe past this view change (degrees). [default: 10]")] = None,
    max_keyframes: Annotated[int | None, typer.Option(help="Keyframe budget. [default: 32]")] = None,
    async_mapping: Annotated[bool, typer.Option(
        "--async-mapping", help="Rebuild the map on a worker thread.")] = False,
    config_file: Annotated[Path | None, typer.Option(
        "--config", help="TrackerConfig as JSON; the options above override it.")] = None,
    load_map: Annotated[Path | None, typer.Option(
        help="Relocalise against a saved .kvmap instead of starting a new map.")] = None,
    save_map: Annotated[Path | None, typer.Option(help="Save the final map as a .kvmap file.")] = None,
    rerun: Annotated[Path | None, typer.Option(
        help="Also record the run as a rerun .rrd file.", metavar="FILE.rrd")] = None,
    start: Annotated[int, typer.Option(help="First frame to use.")] = 0,
    stride: Annotated[int, typer.Option(help="Use every N-th frame.")] = 1,
    max_frames: Annotated[int | None, typer.Option(help="Stop after N frames.")] = None,
    fps: Annotated[float, typer.Option(help="Frame rate that stamps an image folder.")] = 30.0,
    min_confidence: Annotated[float, typer.Option(
        help="Confidence filter of points.ply.")] = 0.5,
    voxel_size: Annotated[float | None, typer.Option(
        help="Voxel edge of points.ply (world units; 0 keeps all). [default: auto]")] = None,
) -> None:
    """Track a camera (or an object) through INPUT and write the trajectory and the map."""
    from kvtracker_sdk.io.sources import open_source

    state: CliState = ctx.find_root().obj
    changes = _config_changes(
        resolution=resolution, mode=mode, keyframe_interval=keyframe_interval,
        view_angle=view_angle, max_keyframes=max_keyframes, async_mapping=async_mapping,
    )
    base = _config_file(config_file)
    config = (base or TrackerConfig()).updated(**changes)  # invalid values fail before any load
    box = parse_bbox(bbox) if bbox is not None else None
    selection = FrameSelection(start, stride, max_frames)
    source = open_source(input_path, fps=fps)
    mask_folder = MaskFolder(masks) if masks is not None else None
    chosen = open_backend(backend, weights, device=device, dtype=dtype, threads=threads)
    try:
        tracker = _tracker(config, base, changes, chosen, load_map)
        with tracker:
            if tracker.config.mode is TrackingMode.OBJECT and masks is None and box is None:
                raise ConfigError(
                    "object mode needs the object: pass --masks DIR or --bbox x0,y0,x1,y1"
                )
            description = RunDescription(
                "track", str(input_path), simulated=False,
                details={"weights": weights, "source": repr(source), "load_map": _str(load_map)},
            )
            options = OutputOptions(
                out, rerun=rerun, min_confidence=min_confidence, voxel_size=voxel_size,
                ground_truth=source.ground_truth(),
            )
            frames = read_frames(source, selection, masks=mask_folder, bbox=box)
            run_session(state, tracker, frames, total=selection.count(len(source)),
                        description=description, options=options)
            if save_map is not None:
                _save(tracker, save_map, state)
    finally:
        chosen.close()


def _config_file(path: Path | None) -> TrackerConfig | None:
    """The ``--config`` JSON file as a validated config (None without the option)."""
    if path is None:
        return None
    try:
        return TrackerConfig.from_dict(json.loads(path.read_text(encoding="utf-8")))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"--config {path}: cannot read a JSON config ({exc})") from exc


def _config_changes(**options: Any) -> dict[str, Any]:
    """The ``TrackerConfig`` fields the command-line options set (None: option not given)."""
    keyframing: dict[str, Any] = {}
    if options["keyframe_interval"] is not None:
        keyframing["interval_frames"] = options["keyframe_interval"]
    if options["view_angle"] is not None:
        keyframing["view_angle_deg"] = options["view_angle"]
    if options["max_keyframes"] is not None:
        keyframing["budget"] = {"max_keyframes": options["max_keyframes"]}
    changes: dict[str, Any] = {"keyframing": keyframing} if keyframing else {}
    for name in ("resolution", "mode"):
        if options[name] is not None:
            changes[name] = options[name]
    if options["async_mapping"]:
        changes["threading"] = {"async_mapping": True}
    return changes


def _tracker(
    config: TrackerConfig,
    base: TrackerConfig | None,
    changes: dict[str, Any],
    backend: Any,
    load_map: Path | None,
) -> Any:
    """A new tracker with ``config``, or with ``--load-map`` one relocalising against the saved
    map (whose saved config is the base unless ``--config`` is given; the options change it)."""
    from kvtracker_sdk.tracking.tracker import Tracker

    if load_map is None:
        return Tracker(config, backend)
    override = base.updated(**changes) if base is not None else (changes or None)
    return Tracker.from_map(load_map, backend, override)


def _save(tracker: Any, path: Path, state: CliState) -> None:
    if tracker.keyframe_map is None:
        raise MapError(f"no map was built, nothing to save to {path}")
    info = tracker.save_map(path)
    if not state.quiet:
        typer.echo(f"map        saved {path} ({info.num_keyframes} keyframes, "
                   f"{info.file_size / 1e6:.1f} MB)")


def _str(path: Path | None) -> str | None:
    return None if path is None else str(path)


def register(app: typer.Typer) -> None:
    app.command("track", epilog=EXIT_CODES_EPILOG)(track)

"""``kvtracker track INPUT``: track a camera (or an object) through a video or an image sequence."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from kvtracker_sdk.cli.failures import EXIT_CODES_EPILOG, reports_errors
from kvtracker_sdk.cli.live_outputs import LiveOptions, live_outputs
from kvtracker_sdk.cli.logging_setup import CliState
from kvtracker_sdk.cli.number_options import MAX_PORT, finite
from kvtracker_sdk.cli.outputs import RunDescription
from kvtracker_sdk.cli.progress import busy
from kvtracker_sdk.cli.session import OutputOptions, check_outputs, run_session
from kvtracker_sdk.config import TrackerConfig, TrackingMode
from kvtracker_sdk.errors import ConfigError, MaskError
from kvtracker_sdk.io.sources.depth_frames import DepthFolder
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.runs.backends import DEFAULT_WEIGHTS, BackendKind, ComputeDtype, open_backend
from kvtracker_sdk.runs.frames import FrameSelection, MaskFolder, parse_bbox, read_frames
from kvtracker_sdk.runs.run_loop import BadFramePolicy
from kvtracker_sdk.types import StateReason

if TYPE_CHECKING:
    from kvtracker_sdk.tracking.facade.tracker import Tracker

__all__ = ["register", "track"]

_log = get_logger(__name__)

_OUT_HELP = "Output folder: trajectory.txt, keyframes.json, points.ply, trajectory.png, run.json."


@reports_errors
def track(
    ctx: typer.Context,
    input_path: Annotated[str, typer.Argument(
        metavar="INPUT", help="Video file, image folder, TUM folder (rgb.txt), 7-Scenes sequence, "
        "camera index (0) or stream URL (rtsp://...).", show_default=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help=_OUT_HELP)] = Path("kvtracker_out"),
    weights: Annotated[str, typer.Option(
        help="Checkpoint: a .safetensors file, a folder holding one, a preset (da3-small) or a "
        "hub id ([hub] extra to download).")] = DEFAULT_WEIGHTS,
    backend: Annotated[BackendKind, typer.Option(
        help="Inference runtime: torch, onnx ([onnx] extra) or openvino ([openvino] extra; "
        "exporting a checkpoint for it needs [onnx] too); auto: the one `kvtracker tune` chose on "
        "this machine for these weights, resolution and keyframe budget (else torch).")
    ] = BackendKind.AUTO,
    device: Annotated[str, typer.Option(
        help="cpu, cuda, cuda:1, ... (openvino: cpu, gpu, npu)")] = "cpu",
    dtype: Annotated[ComputeDtype | None, typer.Option(
        help="Compute dtype (torch), precision (openvino; mixed: bf16 encoder, fp32 decoder "
             "and camera head). [default: float32, or auto's]")
    ] = None,
    threads: Annotated[int | None, typer.Option(min=1, max=4096,
        help="CPU threads for inference (torch, onnx, openvino). [default: the runtime's choice]")] = None,
    resolution: Annotated[int | None, typer.Option(
        help="Model input side d (224, 308, 504, 518): Pi3 at most d² pixels, DA3 the longest "
             "side. [default: the family's, Pi3 308, DA3 504]")] = None,
    mode: Annotated[TrackingMode | None, typer.Option(
        help="scene: the camera in a static scene; object: a masked object. [default: scene]")] = None,
    masks: Annotated[Path | None, typer.Option(
        help="Object mode: folder with one mask image per frame (natural order). [default: none]")] = None,
    bbox: Annotated[str | None, typer.Option(
        help="Object mode: x0,y0,x1,y1 box (pixels) used for every frame (with --bbox-once: "
        "the first frame only). [default: none]")] = None,
    bbox_once: Annotated[bool, typer.Option(
        "--bbox-once", help="Object mode: give --bbox with the first frame only; the tracker "
        "predicts the object's region in every frame after it (object.json). [default: off]")] = False,
    keyframe_interval: Annotated[int | None, typer.Option(min=1,
        help="Scene mode: a keyframe every N frames. [default: 50]")] = None,
    view_angle: Annotated[float | None, typer.Option(min=0, max=180, callback=finite,
        help="Object mode: new keyframe past this view change (degrees). [default: 10]")] = None,
    max_keyframes: Annotated[int | None, typer.Option(min=1,
        help="Keyframe budget. [default: 32; object mode 60]")] = None,
    cache_dtype: Annotated[str | None, typer.Option(
        help="How the map's K/V are kept and saved: backend (its dtype), int8 or fp8 "
             "(quantised, ~1.94x smaller than bf16; torch backend). [default: backend]",
        metavar="backend|int8|fp8")] = None,
    async_mapping: Annotated[bool | None, typer.Option(
        "--async-mapping/--sync-mapping", help="Rebuild the map on a worker thread. "
        "[default: async for a camera or stream, sync for files]")] = None,
    camera: Annotated[Path | None, typer.Option(
        help="Intrinsics file (JSON, or YAML with the [yaml] extra: fx fy cx cy width "
        "height distortion, or ROS CameraInfo). [default: the dataset's published ones, if any]")] = None,
    realtime: Annotated[bool, typer.Option(
        "--realtime", help="Replay a file at its own frame rate, like a live camera. [default: off]")] = False,
    config_file: Annotated[Path | None, typer.Option(
        "--config", help="TrackerConfig as JSON; the options above override it. [default: none]")] = None,
    load_map: Annotated[Path | None, typer.Option(
        help="Relocalise against a saved .kvmap instead of starting a new map. [default: none]")] = None,
    rebuild_map: Annotated[bool, typer.Option(
        "--rebuild-map", help="With --load-map: add keyframes even to a map whose frames another "
        "preprocessing made (an older SDK); else such a map is only tracked against. [default: off]")] = False,
    save_map: Annotated[Path | None, typer.Option(help="Save the final map as a .kvmap file. [default: none]")] = None,
    rerun: Annotated[Path | None, typer.Option(
        help="Also record the run as a rerun .rrd file ([viz] extra). [default: none]", metavar="FILE.rrd")] = None,
    start: Annotated[int, typer.Option(min=0, help="First frame to use.")] = 0,
    stride: Annotated[int, typer.Option(min=1, help="Use every N-th frame.")] = 1,
    max_frames: Annotated[int | None, typer.Option(min=1, help="Stop after N frames. [default: all]")] = None,
    on_bad_frame: Annotated[BadFramePolicy, typer.Option(
        help="A frame that cannot be used (undecodable, another size, bad mask): stop the run "
        "there (outputs so far kept, exit code 3) or skip it (counted in the summary and "
        "run.json).")] = BadFramePolicy.STOP,
    fps: Annotated[float, typer.Option(min=1e-3, max=1e6, callback=finite, help="Frame rate that stamps an image folder.")] = 30.0,
    min_confidence: Annotated[float, typer.Option(min=0, max=1, callback=finite,
        help="Confidence filter of points.ply.")] = 0.5,
    voxel_size: Annotated[float | None, typer.Option(min=0, callback=finite,
        help="Voxel edge of points.ply (world units; 0 keeps all). [default: auto]")] = None,
    view: Annotated[bool, typer.Option(
        "--view", help="Serve a live 3D view on http://127.0.0.1:PORT while tracking ([view] extra). [default: off]")] = False,
    view_port: Annotated[int, typer.Option(
        min=0, max=MAX_PORT, help="Port of --view (0: any free port).")] = 8080,
    ros2_bag: Annotated[Path | None, typer.Option(
        help="Also write a ROS 2 bag (MCAP) into this new folder ([ros] extra). [default: none]", metavar="DIR")] = None,
    depth: Annotated[Path | None, typer.Option(
        help="RGB-D: depth images registered to the frames (a TUM sequence or depth/ folder with "
        "depth.txt, matched by time; or images matched by position). The map becomes metric. [default: none]",
        metavar="DIR")] = None,
    depth_scale: Annotated[float | None, typer.Option(
        help="Metres per unit of the depth images (RealSense 0.001). [default: TUM's 1/5000 "
        "with depth.txt; needed otherwise for integer images]")] = None,
) -> None:
    """Track a camera (or an object) through INPUT and write the trajectory and the map."""
    from kvtracker_sdk.io.sources.live_sources import is_live_spec
    from kvtracker_sdk.runs.inputs import open_input
    from kvtracker_sdk.runs.session import open_tracker

    state: CliState = ctx.find_root().obj
    live = is_live_spec(input_path) and not Path(input_path).exists()
    if async_mapping is None and live:  # live: rebuilds must not pause tracking
        async_mapping = True
    changes = _config_changes(
        resolution=resolution, mode=mode, keyframe_interval=keyframe_interval,
        view_angle=view_angle, max_keyframes=max_keyframes, async_mapping=async_mapping,
        cache_dtype=cache_dtype,
    )
    base = _config_file(config_file)
    config = (base or TrackerConfig()).updated(**changes)  # invalid values fail before any load
    box = parse_bbox(bbox) if bbox is not None else None
    if bbox_once and box is None:
        raise ConfigError("--bbox-once needs --bbox x0,y0,x1,y1")
    selection = FrameSelection(start, stride, max_frames)
    run_input = open_input(input_path, camera=camera, fps=fps, realtime=realtime)
    source, intrinsics = run_input.source, run_input.camera
    mask_folder = MaskFolder(masks) if masks is not None else None
    depth_folder = DepthFolder(depth) if depth is not None else None
    _check_object_inputs(_effective_mode(config, base, changes, load_map), masks, box,
                         loaded=load_map is not None)
    options = OutputOptions(
        out, rerun=rerun, min_confidence=min_confidence, voxel_size=voxel_size,
        ground_truth=run_input.ground_truth, save_map=save_map,
    )
    check_outputs(options)  # before the weights load and the first frame, not after the run
    backend, dtype, threads, why = _resolve_auto(backend, weights, device, dtype, threads, config)
    chosen = _open_backend(state, backend, weights, device=device, dtype=dtype, threads=threads)
    try:
        # with --load-map: the saved config is the base unless --config is given; options change it
        override = config if load_map is None else (
            base.updated(**changes) if base is not None else (changes or None))
        with open_tracker(override, chosen, run_input, load_map=load_map,
                          rebuild=rebuild_map) as tracker:
            description = RunDescription(
                "track", str(input_path), simulated=False,
                details={"weights": weights, "source": repr(source), "load_map": _str(load_map),
                         "backend_choice": {"backend": backend.value, "dtype": dtype.value,
                                            "threads": threads, "reason": why},
                         "camera": None if intrinsics is None else intrinsics.to_dict()},
            )
            frames = read_frames(source, selection, masks=mask_folder, bbox=box,
                                 bbox_first_only=bbox_once, depth=depth_folder,
                                 depth_scale=depth_scale)
            with live_outputs(LiveOptions(view, view_port, ros2_bag), tracker, state) as outs:
                run_session(state, tracker, frames, total=selection.count(len(source)),
                            description=description, options=outs.around(options),
                            on_bad_frame=on_bad_frame)
            _check_object_found(tracker, load_map)
    finally:
        chosen.close()


def _effective_mode(
    config: TrackerConfig, base: TrackerConfig | None, changes: dict[str, Any], load_map: Path | None
) -> TrackingMode:
    """The mode the run will track in: with ``--load-map`` and neither ``--config`` nor
    ``--mode``, the saved map's (read from its header only)."""
    if load_map is None or base is not None or "mode" in changes:
        return config.mode
    from kvtracker_sdk.io.map_file.map_file import read_map_info

    try:
        return TrackingMode(read_map_info(load_map).mode)
    except ValueError:  # a bad mode field: loading the map reports it as a map error
        return config.mode


def _check_object_found(tracker: Tracker, load_map: Path | None) -> None:
    """After the run (outputs written): MaskError, telling what to pass, when a loaded object
    map's object was searched for in vain (reason OBJECT_NOT_FOUND at the end)."""
    if tracker.reason is StateReason.OBJECT_NOT_FOUND:
        raise MaskError(
            f"the object of {load_map} was not found in the whole frame "
            f"({tracker.config.object.search_frames} frames or more): pass --bbox x0,y0,x1,y1 "
            "--bbox-once (its box on the first frame, which must show it) or --masks DIR"
        )


def _check_object_inputs(
    mode: TrackingMode, masks: Path | None, box: tuple[float, float, float, float] | None,
    *, loaded: bool = False,
) -> None:
    """Object mode needs masks or a box, unless a loaded object map finds the object itself;
    scene mode tracks the whole frame, so a box there would only crop the map's point cloud
    without saying so."""
    if mode is TrackingMode.OBJECT and masks is None and box is None and not loaded:
        raise ConfigError("object mode needs the object: pass --masks DIR or --bbox x0,y0,x1,y1")
    if mode is TrackingMode.SCENE and box is not None:
        raise ConfigError(
            "--bbox is for object mode (--mode object); scene mode tracks the whole frame"
        )


def _resolve_auto(
    kind: BackendKind, weights: str, device: str, dtype: ComputeDtype | None,
    threads: int | None, config: TrackerConfig,
) -> tuple[BackendKind, ComputeDtype, int | None, str]:  # fmt: skip
    """``--backend auto``: the tuned choice (``cli/tune.py``) unless ``--dtype`` or ``--threads``
    says otherwise or the device is not the CPU (tuning measures CPUs); then torch. Returns the
    runtime, dtype, threads and why (recorded in run.json)."""
    if kind is not BackendKind.AUTO:
        return kind, dtype or ComputeDtype.FLOAT32, threads, "--backend given"
    if dtype is not None or threads is not None or device != "cpu":
        why = "--backend auto with --dtype, --threads or a non-CPU --device: torch"
        return BackendKind.TORCH, dtype or ComputeDtype.FLOAT32, threads, why
    from kvtracker_sdk.cli.tune import auto_choice

    budget = config.keyframing.budget.max_keyframes or 32
    chosen, chosen_dtype, chosen_threads, why = auto_choice(
        weights, resolution=config.resolution, keyframes=budget
    )
    return chosen, ComputeDtype(chosen_dtype), chosen_threads, why


def _open_backend(state: CliState, kind: BackendKind, weights: str, **options: Any) -> Any:
    """``open_backend`` under a spinner; an export of the checkpoint to ONNX (minutes for a
    full model, on first use only) is announced as a line when it actually starts."""

    def announce_export(folder: Path) -> None:
        text = (f"exporting {weights} to ONNX for {kind.value} into {folder} (first use only: "
                "the export is cached; minutes for a full model)")
        _log.info(text)
        if state.chatty:
            state.console.print(text, highlight=False, markup=False)

    with busy(state, f"loading the weights {weights}"):
        return open_backend(kind, weights, on_export=announce_export, **options)


def _config_file(path: Path | None) -> TrackerConfig | None:
    """The ``--config`` JSON file as a validated config (None without the option)."""
    if path is None:
        return None
    from kvtracker_sdk.io.files.regular_file import read_regular_text

    text = read_regular_text(path, ConfigError, what="--config")  # a FIFO would block forever
    try:
        return TrackerConfig.from_dict(json.loads(text))
    except (json.JSONDecodeError, RecursionError) as exc:  # RecursionError: deeply nested JSON
        raise ConfigError(f"--config {path}: cannot read a JSON config ({str(exc)[:200]})") from exc


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
    for name in ("resolution", "mode", "cache_dtype"):
        if options[name] is not None:
            changes[name] = options[name]
    if options["async_mapping"] is not None:
        changes["threading"] = {"async_mapping": bool(options["async_mapping"])}
    return changes


def _is_onnx_export(weights: str) -> bool:
    from kvtracker_sdk.backends.onnx_manifest import MANIFEST_NAME

    return (Path(weights) / MANIFEST_NAME).is_file()


def _str(path: Path | None) -> str | None:
    return None if path is None else str(path)


def register(app: typer.Typer) -> None:
    app.command("track", epilog=EXIT_CODES_EPILOG)(track)

"""``kvtracker demo``: the whole pipeline offline, on a fresh machine, with nothing downloaded.

``--mode object`` walks around an object standing on a desk beside a second one (a 12 x 9 x 16 cm
box and a 10 x 10 x 13 cm box, ``SimulatedScene.desk``; with ``--gt``, the sphere where that
path looks), given its box on the first frame only: the tracker separates it from the desk and
its neighbour, predicts its region in every next frame, and ``object.json`` holds the regions,
``T_cam_object`` per frame and the object's frame (up: the desk's normal) and extent.

The simulated backend stands in for the network: it renders frames of a known camera path and
answers with that path's poses through noise and a fresh random Sim(3) per mapping pass (as Pi3
answers in each pass's own frame and scale), and drops its confidence over a "camera covered"
segment. Everything else is the real SDK: the tracker, its state machine, keyframing, gauge
alignment, the writers and the evaluation. Every output says SIMULATED.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from kvtracker_sdk.cli.failures import EXIT_CODES_EPILOG, reports_errors
from kvtracker_sdk.cli.live_outputs import LiveOptions, live_outputs
from kvtracker_sdk.cli.logging_setup import CliState
from kvtracker_sdk.cli.number_options import MAX_PORT, MAX_SIMULATED_FRAMES, finite
from kvtracker_sdk.cli.outputs import RunDescription
from kvtracker_sdk.cli.session import OutputOptions, check_outputs, run_session
from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.runs.run_loop import InputFrame

__all__ = ["SIMULATED_NOTICE", "demo", "register"]

if TYPE_CHECKING:
    import numpy as np

    from kvtracker_sdk.backends.simulated import SimulatedBackend

_log = get_logger(__name__)

SIMULATED_NOTICE = (
    "SIMULATED run: frames and poses come from a simulated backend driven by a known trajectory "
    "(noisy ground truth), not from a neural network; accuracy numbers say nothing about a model."
)


def _parse_size(text: str) -> tuple[int, int]:
    try:
        height, width = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise ConfigError(f"--size {text!r}: expected HEIGHTxWIDTH, e.g. 240x320") from exc
    if min(height, width) < 28 or max(height, width) > 4096:
        raise ConfigError(f"--size {text!r}: frames need at least 28 pixels a side (and at most 4096)")
    return height, width


def _parse_segment(text: str) -> tuple[int, int]:
    try:
        start, stop = (int(v) for v in text.split(":"))
    except ValueError as exc:
        raise ConfigError(f"--loss {text!r}: expected START:STOP frame indices") from exc
    if not 0 <= start < stop:
        raise ConfigError(f"--loss {text!r}: need 0 <= START < STOP")
    return start, stop


@reports_errors
def demo(
    ctx: typer.Context,
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path("kvtracker_demo"),
    gt: Annotated[Path | None, typer.Option(
        "--gt", help="Drive the simulation with this TUM groundtruth.txt instead of the built-in "
        "orbit. [default: none: the orbit]")] = None,
    frames: Annotated[int | None, typer.Option(min=1, max=MAX_SIMULATED_FRAMES,
        help="Frames to run (at 30 Hz). [default: 600 for the orbit, all of --gt]")] = None,
    size: Annotated[str, typer.Option(help="Rendered frame size HEIGHTxWIDTH.")] = "240x320",
    loss: Annotated[str | None, typer.Option(
        help="Frames START:STOP where the camera is covered. [default: 1.5 s from 55 %]")] = None,
    no_loss: Annotated[bool, typer.Option("--no-loss", help="Never lose tracking. [default: off]")] = False,
    noise_cm: Annotated[float | None, typer.Option(min=0, max=1000, callback=finite,
        help="Pose noise per axis (cm). [default: 1.0; 0.3 on the desk, seen from 0.5 m]")] = None,
    noise_deg: Annotated[float | None, typer.Option(min=0, max=180, callback=finite,
        help="Rotation noise (degrees). [default: 0.3; 0.1 on the desk]")] = None,
    seed: Annotated[int, typer.Option(min=0, max=2**63 - 1, help="Seed of the path and the noise.")] = 0,
    resolution: Annotated[int, typer.Option(min=14, max=4096, help="Model input side d (224, 308, 518).")] = 308,
    mode: Annotated[str, typer.Option(
        help="scene: track the camera; object: walk around an object on a desk beside another, "
        "tracked from its box on the first frame only (the tracker predicts its region in every "
        "next frame).")] = "scene",
    keyframe_interval: Annotated[int, typer.Option(min=1, help="A keyframe every N frames.")] = 50,
    async_mapping: Annotated[bool, typer.Option(
        "--async-mapping", help="Rebuild the map on a worker thread. [default: off]")] = False,
    rerun: Annotated[Path | None, typer.Option(
        help="Also record the run as a rerun .rrd file ([viz] extra). [default: none]", metavar="FILE.rrd")] = None,
    voxel_size: Annotated[float | None, typer.Option(min=0, callback=finite,
        help="Voxel edge of points.ply (0 keeps all). [default: auto]")] = None,
    view: Annotated[bool, typer.Option(
        "--view", help="Serve a live 3D view on http://127.0.0.1:PORT while tracking ([view] extra). [default: off]")] = False,
    view_port: Annotated[int, typer.Option(
        min=0, max=MAX_PORT, help="Port of --view (0: any free port).")] = 8080,
    save_map: Annotated[Path | None, typer.Option(help="Save the final map as a .kvmap file. [default: none]")] = None,
    ros2_bag: Annotated[Path | None, typer.Option(
        help="Also write a ROS 2 bag (MCAP) into this new folder ([ros] extra). [default: none]", metavar="DIR")] = None,
) -> None:
    """Run the tracker offline on a simulated hand-held camera and write every output."""
    from kvtracker_sdk.backends.simulated import SimulatedBackend
    from kvtracker_sdk.backends.simulated_scene import GroundTruth, SimulatedScene
    from kvtracker_sdk.cli.demo_trajectory import default_loss_segment, desk_orbit, handheld_orbit
    from kvtracker_sdk.config import TrackerConfig
    from kvtracker_sdk.io.files.trajectory import Trajectory
    from kvtracker_sdk.runs.session import open_tracker

    state: CliState = ctx.find_root().obj
    image_size = _parse_size(size)
    if mode not in ("scene", "object"):
        raise ConfigError(f"--mode {mode!r}: expected scene or object")
    if frames is not None and frames < 1:
        raise ConfigError(f"--frames must be >= 1, got {frames}")
    check_outputs(OutputOptions(out, rerun=rerun, save_map=save_map))  # before the first frame
    if gt is not None:
        truth = GroundTruth.from_tum(gt, rate_hz=30.0)
        if frames is not None:
            truth = GroundTruth(truth.timestamps[:frames].copy(), truth.poses[:frames].copy())
    elif mode == "object":  # an object on a desk beside another: what object apps start with
        truth = desk_orbit(frames or 600, seed=seed)
    else:
        truth = handheld_orbit(frames or 600, seed=seed)
    segment = None if no_loss else (_parse_segment(loss) if loss else default_loss_segment(len(truth)))
    desk = mode == "object" and gt is None
    # the desk is seen from 0.5 m, not 1.2 m: the same relative pose error is a third
    noise_cm = noise_cm if noise_cm is not None else (0.3 if desk else 1.0)
    noise_deg = noise_deg if noise_deg is not None else (0.1 if desk else 0.3)
    backend = SimulatedBackend(
        truth, translation_noise_m=noise_cm / 100.0, rotation_noise_deg=noise_deg,
        loss_segments=[segment] if segment else [], seed=seed,
        scene=SimulatedScene.desk(truth.poses) if desk else None, object_in_view=desk,
    )
    config = TrackerConfig.from_dict({
        "mode": mode,
        "resolution": resolution,
        "keyframing": {"interval_frames": keyframe_interval},
        "threading": {"async_mapping": async_mapping},
    })
    if state.chatty:
        typer.echo(SIMULATED_NOTICE, err=True)
    else:
        _log.warning("simulated run", notice=SIMULATED_NOTICE)
    description = RunDescription(
        "demo", str(gt) if gt else ("built-in walk around an object on a desk" if desk
                                    else "built-in hand-held orbit"), simulated=True,
        details={"notice": SIMULATED_NOTICE, "frames": len(truth), "size": list(image_size),
                 "loss_segment": list(segment) if segment else None, "seed": seed,
                 "noise_cm": noise_cm, "noise_deg": noise_deg, "mode": mode},
    )
    options = OutputOptions(
        out, rerun=rerun, voxel_size=voxel_size,
        ground_truth=Trajectory(truth.timestamps, truth.poses), write_ground_truth=True,
        save_map=save_map,
    )
    rendered = (
        InputFrame(f.image, f.timestamp, bbox=_first_box(backend, f.index, f.T_world_cam,
                                                         image_size, mode))
        for f in backend.frames(image_size, textured=True)
    )
    with open_tracker(config, backend) as tracker, \
            live_outputs(LiveOptions(view, view_port, ros2_bag), tracker, state) as live:
        run_session(state, tracker, rendered, total=len(truth), description=description,
                    options=live.around(options), announce_states=True)


def _first_box(
    backend: SimulatedBackend, index: int, T_world_cam: np.ndarray, size: tuple[int, int],
    mode: str,
) -> tuple[float, float, float, float] | None:
    """Object mode: the object's true silhouette box on frame 0 (a user's tap), nothing after."""
    if mode != "object" or index != 0:
        return None
    box = backend.scene.object_box(T_world_cam, size)
    if box is None:
        raise ConfigError("the object is not in view on the first frame of the path")
    return box


def register(app: typer.Typer) -> None:
    app.command("demo", epilog=EXIT_CODES_EPILOG)(demo)

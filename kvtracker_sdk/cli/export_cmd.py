"""``kvtracker export colmap|nerfstudio RUN_OR_MAP OUT``: a run's cameras and points for the
reconstruction tools (COLMAP text model; nerfstudio ``transforms.json`` + ``points.ply``).

    kvtracker track frames/ --weights ... --out run/ --save-map run/map.kvmap
    kvtracker export colmap run/ colmap/                 # keyframe cameras, images, points
    kvtracker export colmap run/ colmap/ --all-frames    # + every tracked frame of the input
    kvtracker export nerfstudio room.kvmap ns/           # a map file works too

Camera (``io/exports/export_camera.py``): ``--camera FILE`` or ``--intrinsics fx,fy,cx,cy,W,H`` (a
calibration, pixels, at any image size: undistorted and rescaled to the map's); by default the
camera stored in the map (``kvtracker track --camera``, a dataset's published intrinsics, or the
network's predicted camera); only without any, one focal length fitted to the keyframes' points
with the principal point at the centre, refused when implausible (under a tenth of the image
width) unless ``--force-fitted-focal``.
"""

from __future__ import annotations

import enum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from kvtracker_sdk.cli.failures import EXIT_CODES_EPILOG, reports_errors
from kvtracker_sdk.cli.logging_setup import CliState
from kvtracker_sdk.errors import ConfigError

if TYPE_CHECKING:
    from kvtracker_sdk.geometry.camera import Camera

__all__ = ["ExportFormat", "export", "register"]


class ExportFormat(str, enum.Enum):
    COLMAP = "colmap"
    NERFSTUDIO = "nerfstudio"


@reports_errors
def export(
    ctx: typer.Context,
    kind: Annotated[ExportFormat, typer.Argument(metavar="FORMAT", help="colmap or nerfstudio.")],
    run_or_map: Annotated[Path, typer.Argument(
        metavar="RUN_OR_MAP", help="A .kvmap file, or a run folder holding one.")],
    out: Annotated[Path, typer.Argument(metavar="OUT", help="Output folder (created).")],
    all_frames: Annotated[bool, typer.Option(
        "--all-frames", help="Also every tracked frame (a `track` run folder, scene mode). [default: off]")] = False,
    intrinsics: Annotated[str | None, typer.Option(
        help="Calibration fx,fy,cx,cy,W,H (pixels; pixel centres at integers). [default: the "
        "camera stored in the map, else fitted to its points]")
    ] = None,
    camera: Annotated[Path | None, typer.Option(
        help="Calibration file (JSON/YAML: fx fy cx cy width height distortion, or ROS "
        "CameraInfo), instead of --intrinsics. [default: none]")] = None,
    force_fitted_focal: Annotated[bool, typer.Option(
        "--force-fitted-focal", help="Export a fitted focal even when it is implausible (under "
        "a tenth of the image width). [default: off]")] = False,
    min_confidence: Annotated[float, typer.Option(help="Confidence filter of the points.")] = 0.5,
    pixel_stride: Annotated[int, typer.Option(
        help="Keep every N-th keyframe pixel in each direction as a point.")] = 2,
) -> None:
    """Export a run's (or a map's) cameras, images and points for COLMAP or nerfstudio."""
    from kvtracker_sdk.io.exports.colmap_text import write_colmap_text
    from kvtracker_sdk.io.exports.nerfstudio import write_nerfstudio
    from kvtracker_sdk.io.exports.run_reconstruction import find_map, load_reconstruction
    from kvtracker_sdk.io.sources.camera_files import read_camera_file

    state: CliState = ctx.find_root().obj
    if intrinsics is not None and camera is not None:
        raise ConfigError("give --camera or --intrinsics, not both")
    given = _parse_intrinsics(intrinsics) if intrinsics else (
        read_camera_file(camera) if camera is not None else None)
    find_map(run_or_map)  # a clear error for a folder without a map, before anything loads
    reconstruction = load_reconstruction(run_or_map, all_frames=all_frames, intrinsics=given,
                                         min_confidence=min_confidence, stride=pixel_stride,
                                         force_fitted_focal=force_fitted_focal)
    if kind is ExportFormat.COLMAP:
        written = write_colmap_text(reconstruction, out)
    else:
        written = write_nerfstudio(reconstruction, out)
    if not state.quiet:
        typer.echo(f"{kind.value}: {len(reconstruction.images)} cameras, "
                   f"{len(reconstruction.points)} points -> {written} "
                   f"(model points off the pinhole by {reconstruction.pinhole_residual_px:.2f} px "
                   f"median before placing them on their rays)")


def _parse_intrinsics(text: str) -> Camera:
    """``fx,fy,cx,cy,W,H`` as a camera of a W x H image (the export rescales it to the map's)."""
    from kvtracker_sdk.geometry.camera import Camera

    try:
        fx, fy, cx, cy, width, height = (float(v) for v in text.split(","))
        return Camera(fx, fy, cx, cy, int(width), int(height))
    except ValueError as exc:  # InputError (bad values) is a ValueError too
        raise ConfigError(f"--intrinsics {text!r}: expected fx,fy,cx,cy,W,H ({exc})") from exc


def register(app: typer.Typer) -> None:
    app.command("export", epilog=EXIT_CODES_EPILOG)(export)

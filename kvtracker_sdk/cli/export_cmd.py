"""``kvtracker export colmap|nerfstudio RUN_OR_MAP OUT``: a run's cameras and points for the
reconstruction tools (COLMAP text model; nerfstudio ``transforms.json`` + ``points.ply``).

    kvtracker track frames/ --weights ... --out run/ --save-map run/map.kvmap
    kvtracker export colmap run/ colmap/                 # keyframe cameras, images, points
    kvtracker export colmap run/ colmap/ --all-frames    # + every tracked frame of the input
    kvtracker export nerfstudio room.kvmap ns/           # a map file works too

Intrinsics: ``--intrinsics fx,fy,cx,cy,W,H`` (a calibration, pixels, at any image size: it is
rescaled to the map's) or, by default, one focal length fitted to the keyframes' points with
the principal point at the centre (the model predicts geometry, not a calibration).
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
    from kvtracker_sdk.io.intrinsics import PinholeIntrinsics

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
        help="Calibration fx,fy,cx,cy,W,H (pixels; pixel centres at integers). "
        "[default: fitted to the map's points]")
    ] = None,
    min_confidence: Annotated[float, typer.Option(help="Confidence filter of the points.")] = 0.5,
    pixel_stride: Annotated[int, typer.Option(
        help="Keep every N-th keyframe pixel in each direction as a point.")] = 2,
) -> None:
    """Export a run's (or a map's) cameras, images and points for COLMAP or nerfstudio."""
    from kvtracker_sdk.io.colmap_text import write_colmap_text
    from kvtracker_sdk.io.nerfstudio import write_nerfstudio
    from kvtracker_sdk.io.run_reconstruction import find_map, load_reconstruction

    state: CliState = ctx.find_root().obj
    camera = _parse_intrinsics(intrinsics, find_map(run_or_map)) if intrinsics else None
    reconstruction = load_reconstruction(run_or_map, all_frames=all_frames, intrinsics=camera,
                                         min_confidence=min_confidence, stride=pixel_stride)
    if kind is ExportFormat.COLMAP:
        written = write_colmap_text(reconstruction, out)
    else:
        written = write_nerfstudio(reconstruction, out)
    if not state.quiet:
        typer.echo(f"{kind.value}: {len(reconstruction.images)} cameras, "
                   f"{len(reconstruction.points)} points -> {written} "
                   f"(model points off the pinhole by {reconstruction.pinhole_residual_px:.2f} px "
                   f"median before placing them on their rays)")


def _parse_intrinsics(text: str, map_path: Path) -> PinholeIntrinsics:
    """``fx,fy,cx,cy,W,H`` rescaled to the map's resolution."""
    from kvtracker_sdk.io.intrinsics import PinholeIntrinsics
    from kvtracker_sdk.io.map_file import read_map_info

    try:
        fx, fy, cx, cy, width, height = (float(v) for v in text.split(","))
        camera = PinholeIntrinsics(fx, fy, cx, cy, int(width), int(height))
    except ValueError as exc:
        raise ConfigError(f"--intrinsics {text!r}: expected fx,fy,cx,cy,W,H ({exc})") from exc
    map_height, map_width = read_map_info(map_path).resolution
    return camera.resized(map_width, map_height)


def register(app: typer.Typer) -> None:
    app.command("export", epilog=EXIT_CODES_EPILOG)(export)

"""``kvtracker map info PATH``: what a ``.kvmap`` file holds, from its header alone.

Reads and validates the header (never the tensor data, so it is instant on a large map and safe
on an untrusted file) and prints the model that made the map (a map loads only with a backend of
the same fingerprint), its resolution, keyframes, cache size, mode and the camera's intrinsics (if saved). ``--json`` prints the
same as one JSON object.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from kvtracker_sdk.cli.failures import EXIT_CODES_EPILOG, reports_errors

if TYPE_CHECKING:
    from kvtracker_sdk.io.map_file.map_format import MapInfo

__all__ = ["map_app", "map_info", "register"]

map_app = typer.Typer(help="Inspect map files (.kvmap).", no_args_is_help=True)


def describe_map(info: MapInfo, path: Path) -> dict[str, Any]:
    """The header's facts as a JSON-ready dict."""
    backend = info.backend
    return {
        "path": str(path),
        "format_version": info.format_version,
        "sdk_version": info.sdk_version,
        "created_utc": info.created_utc.isoformat(),
        "model": backend.model,
        "family": backend.family,
        "fingerprint": info.fingerprint,
        "saved_by_runtime": backend.backend,
        "resolution_hw": list(info.resolution),
        "preprocessing": info.preprocessing,
        "cache_dtype": info.dtype,
        "keyframe_encoding": info.keyframe_encoding,
        "cache_layout": {
            "global_layers": list(info.layout.block_indices),
            "heads": info.layout.num_heads,
            "head_dim": info.layout.head_dim,
        },
        "tokens_per_frame": info.tokens_per_frame,
        "keyframes": info.num_keyframes,
        "keyframe_ids": list(info.keyframe_ids),
        "generation": info.generation,
        "mode": info.mode,
        "gauge_scale": info.gauge.scale,
        "cache_bytes": info.cache_nbytes,
        "file_bytes": info.file_size or path.stat().st_size,
        "user_metadata": dict(info.user_metadata),
        "camera": None if info.camera is None else {
            **info.camera.to_dict(),
            "source": None if info.camera_source is None else info.camera_source.value,
        },
    }


def _text(facts: dict[str, Any]) -> str:
    layout = facts["cache_layout"]
    height, width = facts["resolution_hw"]
    lines = [
        f"map        {facts['path']}",
        f"format     v{facts['format_version']}, saved by kvtracker-sdk {facts['sdk_version']} "
        f"on {facts['created_utc']}",
        f"model      {facts['model']} (family {facts['family']}, fingerprint {facts['fingerprint']})",
        f"mode       {facts['mode']}, input {height}x{width} ({facts['preprocessing']}), cache "
        f"{facts['cache_dtype']}",
        f"keyframes  {facts['keyframes']} (ids {facts['keyframe_ids']}), generation "
        f"{facts['generation']}, stored {facts['keyframe_encoding']}",
        f"cache      {facts['cache_bytes'] / 1e6:.1f} MB: {len(layout['global_layers'])} layers x "
        f"{layout['heads']} heads x {layout['head_dim']} dims, {facts['tokens_per_frame']} "
        f"tokens/frame",
        f"file       {facts['file_bytes'] / 1e6:.1f} MB",
    ]
    camera = facts["camera"]
    if camera is not None:
        lines.append(
            f"camera     fx {camera['fx']:.6g} fy {camera['fy']:.6g} cx {camera['cx']:.6g} "
            f"cy {camera['cy']:.6g} at {camera['width']}x{camera['height']} px ({camera['source']})"
        )
    if facts["user_metadata"]:
        lines.append(f"metadata   {facts['user_metadata']}")
    return "\n".join(lines)


@reports_errors
def map_info(
    ctx: typer.Context,
    path: Annotated[Path, typer.Argument(help="A .kvmap file.", show_default=False)],
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object. [default: off]")] = False,
) -> None:
    """Show what a map file holds (header only; the tensors are not read)."""
    from kvtracker_sdk.io.map_file.map_file import read_map_info

    del ctx  # read by reports_errors (-v shows tracebacks)
    facts = describe_map(read_map_info(path), path)
    typer.echo(json.dumps(facts, indent=2) if as_json else _text(facts))


def register(app: typer.Typer) -> None:
    map_app.command("info", epilog=EXIT_CODES_EPILOG)(map_info)
    app.add_typer(map_app, name="map")

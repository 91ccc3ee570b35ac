"""``kvtracker export-onnx --out DIR``: export a checkpoint to ONNX graphs for ``--backend onnx``.

    kvtracker export-onnx --weights model.safetensors --out pi3-onnx/
    kvtracker export-onnx --weights da3-small --out da3-small-onnx/           # a model name
    kvtracker export-onnx --random-weights --config large --out pi3-random/   # no checkpoint
    kvtracker export-onnx --random-weights --config da3-small --out da3-random/
    kvtracker track video.mp4 --backend onnx --weights pi3-onnx/

Writes the graphs, one shared ``weights.bin`` and ``manifest.json`` (see
``kvtracker_sdk/export_onnx``), after checking them against PyTorch; prints a summary
(``--json``: the manifest). Every size (frames, resolution, cache length) stays dynamic, so one
export serves any ``--resolution``. The full model takes several minutes and ~10 GB of memory.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from kvtracker_sdk.cli.failures import EXIT_CODES_EPILOG, reports_errors
from kvtracker_sdk.cli.logging_setup import CliState
from kvtracker_sdk.errors import ConfigError
from kvtracker_sdk.runs.backends import DEFAULT_WEIGHTS

if TYPE_CHECKING:
    from pydantic import BaseModel

    from kvtracker_sdk.backends.onnx_manifest import OnnxManifest

__all__ = ["export_onnx_command", "register"]


def parse_size(text: str) -> tuple[int, int]:
    """"126x168" -> (126, 168)."""
    height, sep, width = text.lower().partition("x")
    if not sep or not height.isdigit() or not width.isdigit():
        raise ConfigError(f"--check-size must look like 126x168 (H x W in pixels), got {text!r}")
    return int(height), int(width)


def load_config(text: str) -> BaseModel:
    """An architecture: a preset name of a family (``large`` / ``pi3``, ``da3-small`` ...
    ``da3-giant``) or a JSON file holding one family's configuration."""
    from pydantic import ValidationError

    from kvtracker_sdk.models.registry import FAMILIES

    if not Path(text).exists():
        for family in FAMILIES.values():
            if (preset := family.preset_config(text)) is not None:
                return preset
    path = Path(text)
    if not path.is_file():
        names = ", ".join(name for family in FAMILIES.values() for name in family.preset_names)
        raise ConfigError(
            f"--config is a preset ({names}) or a config JSON file; {text!r} is none of those"
        )
    try:
        raw = path.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read {path}: {exc}") from exc
    errors = []
    for family in FAMILIES.values():
        try:
            return family.config_type.model_validate_json(raw)
        except ValidationError as exc:
            errors.append(f"as a {family.config_type.__name__}: {exc}")
    raise ConfigError(f"{path} is no model family's configuration ({'; '.join(errors)})")


def summary(manifest: OnnxManifest, out_dir: Path) -> str:
    graphs = ", ".join(manifest.graphs)
    worst = max(manifest.check.values()) if manifest.check else float("nan")
    return "\n".join(
        [
            f"export       {out_dir}",
            f"model        {manifest.model} (family {manifest.family}, fingerprint "
            f"{manifest.fingerprint})",
            f"graphs       {graphs} (opset {manifest.opset}, {manifest.dtype})",
            f"weights      {manifest.weights_file}: {manifest.weights_bytes / 1e6:.1f} MB",
            f"check        max |ORT - PyTorch| {worst:.2e} at {manifest.check_resolution[0]}x"
            f"{manifest.check_resolution[1]}",
            f"use it with  kvtracker track INPUT --backend onnx --weights {out_dir}",
        ]
    )


@reports_errors
def export_onnx_command(
    ctx: typer.Context,
    out_dir: Annotated[Path, typer.Option(
        "--out", "-o", help="Folder to create (graphs, weights.bin, manifest.json).",
        show_default=False)],
    weights: Annotated[str, typer.Option(
        help="Checkpoint: a model name (pi3, da3-small, ...), a .safetensors file, a folder "
             "holding one, or a hub id ([hub] extra to download).")] = DEFAULT_WEIGHTS,
    config: Annotated[str | None, typer.Option(
        help="A preset ('large' for Pi3, 'da3-small', ...) or a config JSON file. "
             "[default: inferred from the checkpoint]")] = None,
    random_weights: Annotated[bool, typer.Option(
        "--random-weights", help="No checkpoint: random weights of --config (tests, benchmarks). [default: off]")] = False,
    seed: Annotated[int, typer.Option(help="Seed of --random-weights.")] = 0,
    check_size: Annotated[str, typer.Option(
        help="H x W of the ORT-vs-PyTorch check (multiples of 14).")] = "126x168",
    opset: Annotated[int, typer.Option(help="ONNX opset.")] = 20,
    overwrite: Annotated[bool, typer.Option(
        "--overwrite", help="Replace --out if it exists (only once the new export is complete). [default: off]")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print the manifest as JSON. [default: off]")] = False,
) -> None:
    """Export a Pi3 or Depth Anything 3 checkpoint to ONNX graphs that the onnx backend serves."""
    from kvtracker_sdk.export_onnx import export_onnx

    state: CliState = ctx.find_root().obj
    architecture = load_config(config) if config is not None else None
    if random_weights and architecture is None:
        raise ConfigError("--random-weights needs --config (e.g. --config large)")
    if state.chatty:
        state.console.print(f"exporting to {out_dir} (the full model takes several minutes)...")
    manifest = export_onnx(
        out_dir,
        weights=None if random_weights else weights,
        config=architecture,
        seed=seed,
        check_size=parse_size(check_size),
        opset=opset,
        overwrite=overwrite,
    )
    typer.echo(manifest.model_dump_json(indent=2) if as_json else summary(manifest, out_dir))


def register(app: typer.Typer) -> None:
    app.command("export-onnx", epilog=EXIT_CODES_EPILOG)(export_onnx_command)

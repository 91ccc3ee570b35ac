"""The claims of an export manifest, checked against what they describe.

``onnx_integrity`` proves that the files are the ones the manifest lists; this module proves
that the manifest says the truth about them, so that an edited manifest is refused rather than
served. Checked, before any graph runs:

* ``config_hash`` is the hash of ``config`` (recomputed), and ``patch_size`` is the config's;
* every graph's inputs and outputs in the manifest are the ones the family derives from that
  config (names, dtypes and fixed dims: heads, head_dim, widths), and ``layout`` and
  ``extra_tokens_per_frame`` agree with them (number of cached layers, heads, head_dim;
  registers or camera token);
* ``weights_bytes`` is the size of the weights file;
* each graph *file* has the inputs and outputs of its role (read from the graph itself by the
  runtime that loads it: :func:`check_graph_signatures`), so two files swapped between roles —
  both digests valid — are refused.

Every failure is a ``ModelError`` naming the field or graph.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from kvtracker_sdk.backends.onnx_manifest import OnnxManifest, TensorSpec, past_key_name
from kvtracker_sdk.errors import ConfigError, ModelError

__all__ = ["GraphSignature", "check_graph_signatures", "check_manifest_claims"]

# graph role -> (inputs, outputs), each name -> dims (int: fixed; str or None: dynamic)
Dims = tuple[int | str | None, ...]
GraphSignature = tuple[Mapping[str, Dims], Mapping[str, Dims]]


def _expected_graphs(family: str, config: Any) -> dict[str, tuple[tuple[TensorSpec, ...], ...]]:
    """role -> (inputs, outputs) the family derives from its architecture ``config``."""
    specs: dict[str, Callable[[Any], Sequence[Any]]] = {}
    if family == "pi3":
        from kvtracker_sdk.models.pi3.graph_specs import pi3_graphs

        specs["pi3"] = pi3_graphs
    elif family == "da3":
        from kvtracker_sdk.models.da3.graph_specs import da3_graphs

        specs["da3"] = da3_graphs
    if family not in specs:  # read_manifest refused unknown families already
        raise ModelError(f"no graph definitions for family {family!r}")
    try:
        graphs = specs[family](config)
    except ConfigError as exc:
        raise ModelError(f"manifest field 'config' cannot be exported: {exc}") from exc
    return {graph.name: (tuple(graph.inputs), tuple(graph.outputs)) for graph in graphs}


def check_manifest_claims(folder: Path, manifest: OnnxManifest) -> None:
    """``ModelError`` unless the manifest's config, hash, graph specs, layout and weights size
    agree (module docstring). Needs no runtime: it reads the config and one file size."""
    from kvtracker_sdk.models.registry import family_named

    source = folder / "manifest.json"
    family = family_named(manifest.family)
    try:
        config = family.config_type(**manifest.config)
    except (ConfigError, TypeError, ValueError) as exc:
        raise ModelError(f"{source}: field 'config' is not a valid {family.display_name} "
                         f"architecture: {str(exc)[:300]}") from exc
    recomputed = getattr(config, "config_hash", None)
    if recomputed != manifest.config_hash:
        raise ModelError(f"{source}: field 'config_hash' {manifest.config_hash!r} is not the hash "
                         f"of its config ({recomputed!r}): the manifest was edited")
    if getattr(config, "patch_size", None) != manifest.patch_size:
        raise ModelError(f"{source}: field 'patch_size' {manifest.patch_size} is not its "
                         f"config's {getattr(config, 'patch_size', None)}")
    expected = _expected_graphs(manifest.family, config)
    if set(manifest.graphs) != set(expected):
        raise ModelError(f"{source}: field 'graphs' lists {sorted(manifest.graphs)}, a "
                         f"{family.display_name} export has {sorted(expected)}")
    for role, (inputs, outputs) in expected.items():
        spec = manifest.graphs.get(role)
        if spec is None or spec.inputs != inputs or spec.outputs != outputs:
            raise ModelError(f"{source}: field 'graphs.{role}' does not list the inputs and "
                             f"outputs its config gives that graph")
    _check_layout(source, manifest, expected)
    extra = _extra_tokens(manifest.family, expected)
    if manifest.extra_tokens_per_frame != extra:
        raise ModelError(f"{source}: field 'extra_tokens_per_frame' {manifest.extra_tokens_per_frame} "
                         f"is not its graphs' {extra}")
    try:
        size = (folder / manifest.weights_file).stat().st_size
    except OSError as exc:
        raise ModelError(f"{source}: cannot read {manifest.weights_file}: {exc}") from exc
    if size != manifest.weights_bytes:
        raise ModelError(f"{source}: field 'weights_bytes' {manifest.weights_bytes} is not the "
                         f"size of {manifest.weights_file} ({size} bytes)")


def _extra_tokens(family: str, expected: Mapping[str, tuple[tuple[TensorSpec, ...], ...]]) -> int:
    """Tokens per frame besides the patches: Pi3's registers (the decoder's ``hidden_registers``
    [F, R, 2*dim]); DA3's one camera token."""
    if family == "pi3":
        registers = {s.name: s.shape for s in expected["decoder_map"][1]}["hidden_registers"]
        return int(registers[1])
    return 1


def _check_layout(
    source: Path, manifest: OnnxManifest, expected: Mapping[str, tuple[tuple[TensorSpec, ...], ...]]
) -> None:
    """``layout`` against the tracking decoder's past K/V inputs [1, heads, capacity, head_dim]."""
    try:
        layout = manifest.cache_layout
    except (ConfigError, KeyError, TypeError, ValueError) as exc:
        raise ModelError(f"{source}: field 'layout' is malformed: {exc}") from exc
    past = {spec.name: spec.shape for spec in expected["decoder_track"][0]}
    layers = 0
    while past_key_name(layers) in past:
        layers += 1
    shape = past.get(past_key_name(0), ())
    claimed = (layout.num_layers, layout.num_heads, layout.head_dim)
    actual = (layers, shape[1] if len(shape) > 1 else None, shape[3] if len(shape) > 3 else None)
    if claimed != actual:
        raise ModelError(
            f"{source}: field 'layout' claims (layers, num_heads, head_dim) = {claimed}, the "
            f"graphs take {actual}"
        )


def _compatible(claimed: tuple[int | str, ...], actual: Dims) -> bool:
    """A graph's dims against the manifest's: same rank, equal where the manifest fixes one (a
    runtime may report a fixed dim as dynamic, never the other way round)."""
    if len(claimed) != len(actual):
        return False
    return all(
        not isinstance(want, int) or got is None or isinstance(got, str) or got == want
        for want, got in zip(claimed, actual, strict=True)
    )


def check_graph_signatures(manifest: OnnxManifest, signatures: Mapping[str, GraphSignature]) -> None:
    """``ModelError`` unless each graph file takes and returns exactly what its role in the
    manifest says (names, ranks, fixed dims). ``signatures``: role -> (inputs, outputs) read
    from the loaded graph by the runtime."""
    for role, spec in manifest.graphs.items():
        if role not in signatures:
            continue
        inputs, outputs = signatures[role]
        for kind, claimed, actual in (("inputs", spec.inputs, inputs), ("outputs", spec.outputs, outputs)):
            names = {tensor.name for tensor in claimed}
            if names != set(actual):
                raise ModelError(
                    f"graph file {spec.file} (role {role!r}) has {kind} "
                    f"{sorted(actual)[:8]}, its role needs {sorted(names)[:8]}: the manifest "
                    "binds it to the wrong role"
                )
            for tensor in claimed:
                if not _compatible(tensor.shape, actual[tensor.name]):
                    raise ModelError(
                        f"graph file {spec.file} (role {role!r}): {kind[:-1]} {tensor.name} has "
                        f"shape {list(actual[tensor.name])}, the manifest says {list(tensor.shape)}"
                    )

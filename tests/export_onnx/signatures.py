"""Shared check of an export folder: every ``.onnx`` file declares its manifest signature."""

from __future__ import annotations

from pathlib import Path

import onnx

from kvtracker_sdk.backends.onnx_manifest import OnnxManifest


def dims(value: onnx.ValueInfoProto) -> list[int | str]:
    return [d.dim_param or d.dim_value for d in value.type.tensor_type.shape.dim]


def assert_graphs_declare_the_manifest(folder: Path, manifest: OnnxManifest) -> None:
    """Names and (symbolic) dims of every graph's inputs and outputs equal the manifest's, and no
    node keeps the exporter's stack traces (they hold local source paths)."""
    for name, spec in manifest.graphs.items():
        graph = onnx.load(folder / spec.file, load_external_data=False).graph
        assert [(i.name, dims(i)) for i in graph.input] == [
            (s.name, list(s.shape)) for s in spec.inputs
        ], name
        assert [(o.name, dims(o)) for o in graph.output] == [
            (s.name, list(s.shape)) for s in spec.outputs
        ], name
        stack_traces = [p for node in graph.node for p in node.metadata_props if "stack" in p.key]
        assert not stack_traces, name

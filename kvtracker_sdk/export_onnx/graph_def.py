"""``torch.export`` dynamic shapes of a graph (``models.graph_io.GraphDef``, re-exported here).

Dims named in a graph's specs become ``torch.export.Dim`` objects; "height"/"width" are
``patch_size`` times the grid dims, so the exporter knows H and W divide exactly into patches.
"""

from __future__ import annotations

from typing import Any

import torch

from kvtracker_sdk.models.graph_io import GraphDef

__all__ = ["GraphDef", "dynamic_shapes"]


def dynamic_shapes(graph: GraphDef, patch_size: int) -> tuple[Any, ...]:
    """``torch.export`` dynamic shapes of the graph's forward arguments (one ``Dim`` per name)."""
    dims: dict[str, Any] = {}

    def dim(name: str) -> Any:
        if name in ("height", "width"):
            return patch_size * dim("grid_h" if name == "height" else "grid_w")
        if name not in dims:
            dims[name] = torch.export.Dim(name)
        return dims[name]

    per_input = [
        {axis: dim(size) for axis, size in enumerate(spec.shape) if isinstance(size, str)} or None
        for spec in graph.inputs
    ]
    if graph.name == "decoder_track":  # forward(patch_tokens, past_length, past: tuple)
        return (per_input[0], per_input[1], tuple(per_input[2:]))
    return tuple(per_input)

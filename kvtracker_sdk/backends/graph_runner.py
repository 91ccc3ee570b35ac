"""``GraphRunner``: mapping and tracking passes over an export folder's graphs, whatever runs them.

An export (``onnx_manifest``) is a chain of graphs: the encoder, a mapping or tracking decoder,
then the head graphs a ``HeadSet`` needs. Chaining them is the same for every runtime; only how
one graph runs differs. A runtime subclasses ``GraphRunner`` and implements ``_run(graph,
feeds)`` (``OnnxRunner``: ONNX Runtime sessions; ``OpenVinoRunner``: OpenVINO compiled models).

The runner speaks numpy: float32 images in [0, 1], K/V arrays, per-frame outputs in the SDK's
conventions. It knows nothing of ``KVCache`` or uint8 frames (that is ``ExportBackend``'s job) so
that the exporter can run it on its check inputs too. It serves every family: the decoders'
outputs other than K/V are the heads' inputs, fed to the head graphs by name, and the family's
record (``models.registry.family_named(manifest.family)``) picks the head graphs and converts
their outputs.
"""

from __future__ import annotations

import abc
from collections.abc import Sequence

import numpy as np

from kvtracker_sdk.backends.onnx_manifest import (
    OnnxManifest,
    past_key_name,
    past_value_name,
    present_key_name,
    present_value_name,
)
from kvtracker_sdk.models.family import FrameOutputs
from kvtracker_sdk.models.registry import family_named
from kvtracker_sdk.types import HeadSet

__all__ = ["GraphRunner"]


class GraphRunner(abc.ABC):
    """The passes over an export's graphs; subclasses say how one graph runs (``_run``)."""

    def __init__(self, manifest: OnnxManifest) -> None:
        self.manifest = manifest
        self._family = family_named(manifest.family)
        self._outputs = {
            name: [spec.name for spec in graph.outputs] for name, graph in manifest.graphs.items()
        }
        self._inputs = {
            name: [spec.name for spec in graph.inputs] for name, graph in manifest.graphs.items()
        }
        self.num_layers = manifest.cache_layout.num_layers

    @abc.abstractmethod
    def _run(self, graph: str, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Run ``graph`` on ``feeds`` (input name -> array); output name -> array, owned by the
        caller. Runtime failures raise ``BackendError``."""

    def encode(self, images: np.ndarray) -> np.ndarray:
        """float32 [F, 3, H, W] in [0, 1] -> patch tokens [F, h, w, dim]."""
        return self._run("encoder", {"images": images})["patch_tokens"]

    def map(self, images: np.ndarray) -> tuple[FrameOutputs, list[np.ndarray], list[np.ndarray]]:
        """Full attention over keyframes float32 [N, 3, H, W] in [0, 1]: all heads, and per
        cached layer K and V [1, heads, N*T, head_dim]."""
        decoded = self._run("decoder_map", {"patch_tokens": self.encode(images)})
        keys = [decoded.pop(present_key_name(i)) for i in range(self.num_layers)]
        values = [decoded.pop(present_value_name(i)) for i in range(self.num_layers)]
        return self.heads(decoded, HeadSet.ALL, images.shape[-2:]), keys, values

    def track(
        self,
        image: np.ndarray,
        past: Sequence[tuple[np.ndarray, np.ndarray]],
        past_length: int,
        heads: HeadSet,
    ) -> FrameOutputs:
        """One frame float32 [1, 3, H, W] against a cache.

        ``past[i]`` = (K, V) of cached layer ``i``, [1, heads, capacity, head_dim] float32,
        whose first ``past_length`` tokens are the cached ones (the rest is ignored). Arrays
        that are C-contiguous are read in place.
        """
        feeds = {
            "patch_tokens": self.encode(image),
            "past_length": np.asarray(past_length, dtype=np.int64),
        }
        for layer, (key, value) in enumerate(past):
            feeds[past_key_name(layer)] = key
            feeds[past_value_name(layer)] = value
        return self.heads(self._run("decoder_track", feeds), heads, image.shape[-2:])

    def heads(
        self, decoded: dict[str, np.ndarray], heads: HeadSet, image_size: Sequence[int]
    ) -> FrameOutputs:
        """Run the head graphs ``heads`` needs on the decoder's outputs (fed by name), converted
        to the SDK's conventions for images of ``image_size`` (H, W)."""
        outputs: dict[str, np.ndarray] = {}
        for graph in self._family.head_graphs(heads):
            outputs.update(self._run(graph, {name: decoded[name] for name in self._inputs[graph]}))
        height, width = image_size
        return self._family.convert_heads(outputs, heads, (int(height), int(width)))

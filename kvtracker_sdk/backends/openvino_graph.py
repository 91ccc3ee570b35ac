"""An export's ``.onnx`` graph read for OpenVINO, with the node OpenVINO computes differently fixed.

OpenVINO's CPU plugin ignores ``antialias`` for an ONNX ``Resize`` in cubic mode (its ONNX
frontend keeps the flag, the kernel does not apply it: openvinotoolkit/openvino#35893, open in
2026.4). Pi3's encoder resizes its positional embeddings with exactly that node (PyTorch's
``interpolate(mode="bicubic", antialias=True)``, which the exporter writes as ONNX ``Resize``
cubic, antialias=1, exclude_outside=1, a=-0.5, half_pixel): read as is, the encoder's tokens
and the poses differ from ONNX Runtime's far beyond float rounding.

That ONNX node is the filter Pillow's bicubic resize applies (the ONNX operator was specified to
match it), and OpenVINO's ``Interpolate-11`` has it as mode ``bicubic_pillow``: switching the
mode makes the encoder agree with ONNX Runtime within float rounding at every size tried
(figures: ``benchmarks/README.md#figures-behind-the-code``). Depth Anything 3's graphs have no
such node.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

__all__ = ["folds_pillow_resize", "read_graph"]


def _is_antialiased_cubic(node: Any) -> bool:
    if node.get_type_name() != "Interpolate":
        return False
    attributes = node.get_attributes()
    return bool(
        attributes.get("mode") == "cubic"
        and attributes.get("antialias")
        and attributes.get("coordinate_transformation_mode") == "half_pixel"
        and abs(float(attributes.get("cube_coeff", 0.0)) + 0.5) < 1e-6
    )


def read_graph(core: Any, path: Path) -> Any:
    """``path`` (an export's ``.onnx``) as an ``openvino.Model`` computing what ONNX Runtime
    computes (see the module docstring); ``core`` is an ``openvino.Core``."""
    model = core.read_model(str(path))
    for node in model.get_ordered_ops():
        if _is_antialiased_cubic(node):
            node.set_attribute("mode", "bicubic_pillow")
    return model


def folds_pillow_resize(model: Any) -> bool:
    """``model`` has a ``bicubic_pillow`` resize (Pi3's encoder): OpenVINO 2026.4 cannot compile
    it static-shaped (its constant folding wants exactly two axes), so it stays dynamic."""
    return any(
        node.get_type_name() == "Interpolate"
        and node.get_attributes().get("mode") == "bicubic_pillow"
        for node in model.get_ordered_ops()
    )

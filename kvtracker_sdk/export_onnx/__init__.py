"""Export tooling: Pi3 or Depth Anything 3 to a folder of ONNX graphs + ``manifest.json`` (served by ``OnnxBackend``).

Needs the ``[onnx]`` extra (onnx, onnxscript, onnx-ir, onnxruntime) and PyTorch; the command
line is ``kvtracker export-onnx``. See ``exporter.py``.
"""

from kvtracker_sdk.export_onnx.exporter import (
    DEFAULT_CHECK_SIZE,
    DEFAULT_OPSET,
    export_model,
    export_onnx,
)

__all__ = ["DEFAULT_CHECK_SIZE", "DEFAULT_OPSET", "export_model", "export_onnx"]

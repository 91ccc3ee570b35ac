"""Export tooling: Pi3 or Depth Anything 3 to a folder of ONNX graphs + ``manifest.json`` (served by ``OnnxBackend``).

Needs the ``[onnx]`` extra (onnx, onnxscript, onnx-ir, onnxruntime) and PyTorch; the command
line is ``kvtracker export-onnx``. See ``exporter.py``; ``onnx_backend(checkpoint)`` and
``openvino_backend(checkpoint)`` (``reuse.py``) export a checkpoint once and serve it.
"""

from kvtracker_sdk.export_onnx.exporter import (
    DEFAULT_CHECK_SIZE,
    DEFAULT_OPSET,
    export_model,
    export_onnx,
)
from kvtracker_sdk.export_onnx.reuse import exported_folder, onnx_backend, openvino_backend

__all__ = [
    "DEFAULT_CHECK_SIZE",
    "DEFAULT_OPSET",
    "export_model",
    "export_onnx",
    "exported_folder",
    "onnx_backend",
    "openvino_backend",
]

"""Export a Pi3 or Depth Anything 3 checkpoint to ONNX without the installed ``kvtracker`` entry point.

    python export/export_onnx.py --weights model.safetensors --out pi3-onnx/
    python export/export_onnx.py --weights da3-small --out da3-small-onnx/
    python export/export_onnx.py --random-weights --config large --out /tmp/pi3-random/

The same as ``kvtracker export-onnx`` (all its options; ``--help`` lists them): the export logic
lives in the package (``kvtracker_sdk.export_onnx``) so that the command works from an installed
wheel; this file only forwards to it.
"""

from __future__ import annotations

import sys

from kvtracker_sdk.cli.app import app

if __name__ == "__main__":
    app(["export-onnx", *sys.argv[1:]], prog_name="export_onnx.py")

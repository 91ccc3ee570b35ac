"""The command starts fast and is reachable as a module as well as the ``kvtracker`` script."""

from __future__ import annotations

import subprocess
import sys

from kvtracker_sdk import __version__


def test_module_entry_point_prints_the_version() -> None:
    out = subprocess.run([sys.executable, "-m", "kvtracker_sdk.cli", "--version"],
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == f"kvtracker-sdk {__version__}"


def test_building_the_app_loads_no_heavy_library() -> None:
    code = (
        "import sys\n"
        "from kvtracker_sdk.cli.app import app\n"
        "heavy = ('torch', 'cv2', 'onnxruntime', 'rerun', 'matplotlib')\n"
        "print([m for m in heavy if m in sys.modules])\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"

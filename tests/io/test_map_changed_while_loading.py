"""A map file that changes underneath the loader: a typed error, never a signal or a hang.

Both cases run in one child process (a SIGBUS would kill pytest itself, a hang would stall it),
made deterministic by hooks instead of races:

- truncated mid-load: the file is truncated to just after its header the moment the loader
  starts hashing tensor data (the header was read and validated; the tensors were not). A loader
  reading through a memory map then touches pages past the end of the file: SIGBUS.
- a FIFO swapped in: the map is replaced by a FIFO the first time the loader touches the path
  (right after an ``os.stat``, or right before an ``os.open``). A loader that checks the path and
  opens it afterwards then blocks forever in ``open``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import PROJECT_ROOT

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="needs POSIX files and FIFOs")

_CHILD = """
import hashlib, json, os, sys, types
from kvtracker_sdk.errors import MapError
from kvtracker_sdk.io.map_file import map_file, map_tensors
from kvtracker_sdk.io.map_file.map_file import load_map, read_map_info, save_map
from tests.io.map_factory import TRACKER_CONFIG, backend_info, make_map

folder = sys.argv[1]
outcomes = {}

def save(name):
    path = os.path.join(folder, name)
    save_map(path, make_map(layers=4, heads=2, head_dim=64, size=(112, 112)),
             backend_info=backend_info(layers=4, heads=2, head_dim=64),
             tracker_config_json=TRACKER_CONFIG, mode="object")
    return path

def outcome(path):
    try:
        load_map(path)
        return "loaded"
    except MapError as exc:
        return type(exc).__name__

# 1. truncated once tensor data starts being hashed
path = save("truncated.kvmap")
keep = 8 + int.from_bytes(open(path, "rb").read(8), "little") + 16
real_sha256 = hashlib.sha256
def truncating_sha256(*args, **kwargs):
    if os.path.getsize(path) > keep:
        os.truncate(path, keep)
    return real_sha256(*args, **kwargs)
shim = types.SimpleNamespace(sha256=truncating_sha256)
for module in (map_tensors, sys.modules.get("kvtracker_sdk.io.map_file.map_reader")):
    if module is not None and hasattr(module, "hashlib"):
        module.hashlib = shim
outcomes["truncated"] = outcome(path)
for module in (map_tensors, sys.modules.get("kvtracker_sdk.io.map_file.map_reader")):
    if module is not None and hasattr(module, "hashlib"):
        module.hashlib = hashlib

# 2. a FIFO swapped in when the loader first touches the path
path = save("swapped.kvmap")
real_stat, real_open, swapped = os.stat, os.open, []
def swap(target):
    if os.fspath(target) == path and not swapped:
        swapped.append(True)
        os.unlink(path)
        os.mkfifo(path)
def stat_then_swap(target, *args, **kwargs):
    result = real_stat(target, *args, **kwargs)
    swap(target)
    return result
def swap_then_open(target, *args, **kwargs):
    swap(target)
    return real_open(target, *args, **kwargs)
os.stat, os.open = stat_then_swap, swap_then_open
outcomes["fifo"] = outcome(path)
os.stat, os.open = real_stat, real_open
outcomes["fifo_swapped"] = bool(swapped)
print(json.dumps(outcomes))
"""


def test_truncation_or_fifo_during_a_load_gives_a_typed_error(tmp_path: Path) -> None:
    try:
        child = subprocess.run(
            [sys.executable, "-c", _CHILD, str(tmp_path)],
            cwd=PROJECT_ROOT, capture_output=True, text=True, timeout=120,
        )  # fmt: skip
    except subprocess.TimeoutExpired as exc:
        pytest.fail(f"the loader hung (a FIFO swapped in?): {exc.stdout!r}")
    assert child.returncode == 0, (
        f"the loader died (exit {child.returncode}): {child.stderr[-2000:]}"
    )
    outcomes = json.loads(child.stdout.splitlines()[-1])
    assert outcomes == {
        "truncated": "MapCorruptedError",
        "fifo": "MapFormatError",
        "fifo_swapped": True,
    }

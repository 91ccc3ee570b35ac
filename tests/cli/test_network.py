"""``kvtracker demo`` and ``kvtracker track``, with the live viewer and a rerun recording, connect
and bind only to loopback: every ``connect()``/``bind()`` of the process (and of anything it
starts) is traced by ``tests/network_trace.py``.

Both commands run in one fresh interpreter, through the same typer app the ``kvtracker`` entry
point runs (one interpreter start and one torch import instead of two: this test is ``slow``).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

from tests.helpers import PROJECT_ROOT, dev_dependency, shared_path
from tests.network_trace import require_strace, run_traced

COMMANDS = """
import json, sys
from kvtracker_sdk.cli.app import app

out, frames, weights = sys.argv[1:4]
runs = {
    "demo": ["demo", "--out", out + "/demo", "--frames", "12", "--size", "90x120",
             "--resolution", "224", "--view", "--view-port", "0", "--rerun", out + "/demo.rrd"],
    "track": ["track", frames, "--weights", weights, "--out", out + "/track", "--max-frames", "3",
              "--resolution", "224", "--threads", "1", "--view", "--view-port", "0",
              "--rerun", out + "/track.rrd"],
}
codes = {}
for name, args in runs.items():
    try:
        app(args, standalone_mode=False)
        codes[name] = 0
    except SystemExit as exit_:
        codes[name] = exit_.code or 0
print(json.dumps(codes))
"""


@pytest.mark.slow
def test_demo_and_track_with_viewer_and_rerun_stay_on_loopback(tmp_path: Path) -> None:
    dev_dependency("viser")
    dev_dependency("rerun")
    require_strace()
    frames = shared_path("data", "tum_fr2_desk")
    weights = shared_path("golden", "pi3", "weights.safetensors")
    env = {**os.environ, "PYTHONPATH": str(PROJECT_ROOT)}
    run = run_traced([sys.executable, "-c", COMMANDS, str(tmp_path), str(frames), str(weights)],
                     tmp_path / "cli.strace", env=env, timeout=300)
    assert run.process.returncode == 0, run.process.stderr[-4000:]
    assert json.loads(run.process.stdout.strip().splitlines()[-1]) == {"demo": 0, "track": 0}
    assert (tmp_path / "demo.rrd").stat().st_size > 0 and (tmp_path / "track.rrd").stat().st_size
    # the trace saw both viewers' servers: one bind to 127.0.0.1 per command
    servers = [c for c in run.calls if c.call == "bind" and c.host == "127.0.0.1"]
    assert len(servers) >= 2, [c.line for c in run.calls]
    assert [c.line for c in run.outside] == []
